"""Every panel's ``draw()`` (and the preferences') runs headless in the states that matter:
no result, job running, cancel requested, job failed, job finished, result built.

Headless bpy has no regions, so no real ``UILayout`` exists to draw into. ``draw`` is
called with a stand-in whose ``layout`` records every call and checks it against
Blender's own RNA, so a typo fails here as it would in the UI:

* methods and their keyword arguments must exist on ``bpy.types.UILayout``;
* attributes set on a layout (``alert``, ``scale_y``, ...) must be UILayout properties;
* ``prop(data, name)`` needs ``name`` in ``data``'s RNA properties;
* ``operator(idname)`` needs a registered operator, and properties set on the returned
  operator pointer must be that operator's properties;
* every ``icon=`` must be one of Blender's icon identifiers.
"""

from __future__ import annotations

import sys
from types import SimpleNamespace

import pytest

from tests.addon._support import bpy, clean_jobs, fake_engine, registered, user_dir, wait_until  # noqa: F401

_UI = bpy.types.UILayout.bl_rna
_FUNCS = {f.identifier: {p.identifier for p in f.parameters} for f in _UI.functions}
_LAYOUT_PROPS = set(_UI.properties.keys())
_ICONS = {e.identifier for e in _UI.functions["label"].parameters["icon"].enum_items}
_SUBLAYOUTS = {"row", "column", "box", "split", "column_flow", "grid_flow"}


class OperatorProps:
    """Stand-in for the operator properties ``layout.operator()`` returns."""

    def __init__(self, idname: str, rna, log: list):
        object.__setattr__(self, "_idname", idname)
        object.__setattr__(self, "_rna", rna)
        object.__setattr__(self, "_log", log)

    def __setattr__(self, name, value):
        assert name in self._rna.properties.keys(), f"{self._idname} has no property {name!r}"
        self._log.append(("set", self._idname, name, value))


class Layout:
    """A recording, validating stand-in for ``bpy.types.UILayout``."""

    def __init__(self, log: list):
        object.__setattr__(self, "_log", log)

    def __setattr__(self, name, value):
        assert name in _LAYOUT_PROPS, f"UILayout has no property {name!r}"
        self._log.append(("attr", name, value))

    def __getattr__(self, name):
        assert name in _FUNCS, f"UILayout has no method {name!r}"

        def call(*args, **kwargs):
            unknown = set(kwargs) - _FUNCS[name]
            assert not unknown, f"UILayout.{name}() has no arguments {unknown}"
            icon = kwargs.get("icon")
            assert icon is None or icon in _ICONS, f"unknown icon {icon!r}"
            for key in ("text", "heading"):
                assert kwargs.get(key) is None or isinstance(kwargs[key], str), (name, key, kwargs[key])
            self._log.append((name, args, kwargs))
            if name in _SUBLAYOUTS:
                return Layout(self._log)
            if name == "panel":
                return Layout(self._log), Layout(self._log)
            if name == "prop":
                data, prop = args[:2]
                assert prop in data.bl_rna.properties.keys(), f"{type(data).__name__} has no property {prop!r}"
                return None
            if name == "operator":
                idname = args[0] if args else kwargs["operator"]
                mod, op = idname.split(".")
                try:
                    rna = getattr(getattr(bpy.ops, mod), op).get_rna_type()
                except (AttributeError, KeyError):
                    raise AssertionError(f"operator {idname!r} is not registered") from None
                return OperatorProps(idname, rna, self._log)
            return None

        return call


def draw(panel_cls, context=None, owner=None) -> list:
    """Run ``panel_cls.draw`` with a recording layout; returns the call log."""
    log: list = []
    if owner is None:
        stand_in = SimpleNamespace(layout=Layout(log))
    else:  # AddonPreferences: draw reads its own properties
        stand_in = _Proxy(owner, Layout(log))
    panel_cls.draw(stand_in, context or bpy.context)
    return log


class _Proxy:
    def __init__(self, real, layout):
        object.__setattr__(self, "_real", real)
        object.__setattr__(self, "layout", layout)

    def __getattr__(self, name):
        return getattr(self._real, name)


def labels(log) -> list[str]:
    return [c[2].get("text", "") for c in log if c[0] == "label"]


def operators(log) -> list[str]:
    return [c[1][0] for c in log if c[0] == "operator"]


def _panels(extension):
    p = extension.panels
    return [p.main_panel.MOTIONSPLATS_PT_main, p.main_panel.MOTIONSPLATS_PT_clip_main,
            p.reconstruct_panel.MOTIONSPLATS_PT_reconstruct, p.reconstruct_panel.MOTIONSPLATS_PT_clip_reconstruct,
            p.build_panel.MOTIONSPLATS_PT_result]


def _draw_all(extension, prefs):
    logs = {cls.__name__: draw(cls) for cls in _panels(extension)}
    logs["prefs"] = draw(type(prefs), owner=prefs)
    return logs


def test_every_panel_is_checked(extension):
    """The list above covers every registered panel class."""
    panels = {c.__name__ for c in extension.panels.CLASSES if issubclass(c, bpy.types.Panel)}
    assert panels == {c.__name__ for c in _panels(extension)}
    spaces = {c.bl_space_type for c in _panels(extension)}
    assert spaces == {"VIEW_3D", "CLIP_EDITOR"}


def test_stand_in_layout_catches_mistakes(registered):
    log: list = []
    layout = Layout(log)
    with pytest.raises(AssertionError, match="no method"):
        layout.lable(text="x")
    with pytest.raises(AssertionError, match="unknown icon"):
        layout.label(text="x", icon="NOT_AN_ICON")
    with pytest.raises(AssertionError, match="no property"):
        layout.prop(bpy.context.scene.motion_splats_result, "no_such_prop")
    with pytest.raises(AssertionError, match="not registered"):
        layout.operator("motion_splats.no_such_operator")
    with pytest.raises(AssertionError, match="no property"):
        layout.operator("motion_splats.cancel_job").no_such = 1
    with pytest.raises(AssertionError, match="UILayout has no property"):
        layout.colour = 1


def test_panels_draw_without_result_or_job(extension, registered):
    logs = _draw_all(extension, registered)
    assert "No engine job" in labels(logs["MOTIONSPLATS_PT_main"])
    assert labels(logs["MOTIONSPLATS_PT_main"]) == labels(logs["MOTIONSPLATS_PT_clip_main"])
    assert "No result in the scene: reconstruct or import a bundle first" in labels(logs["MOTIONSPLATS_PT_result"])
    assert "motion_splats.finetune" not in operators(logs["MOTIONSPLATS_PT_result"])
    rec = operators(logs["MOTIONSPLATS_PT_reconstruct"])
    assert {"motion_splats.reconstruct", "motion_splats.resume", "motion_splats.import_footage",
            "motion_splats.import_tracking_camera", "motion_splats.import_colmap_camera"} <= set(rec)
    assert rec == operators(logs["MOTIONSPLATS_PT_clip_reconstruct"])
    assert "motion_splats.check_engine" in operators(logs["prefs"])


def test_panels_draw_running_cancelling_failed_finished(extension, registered, tmp_path, clean_jobs):
    jobs, bridge = clean_jobs, extension.addon.bridge
    argv = fake_engine(tmp_path, "train", """
        emit("progress", stage="train", step=30, total=100, loss=0.125, psnr=22.5, eta_s=75)
        try:
            while True:
                time.sleep(0.05)
        except KeyboardInterrupt:
            emit("error", message="interrupted; state saved", fix="re-run with --resume")
            sys.exit(130)
    """)
    job = jobs.start("train", bridge.EngineProcess(argv, cwd=tmp_path), label="Reconstruct")
    assert wait_until(lambda: (jobs.drain(), job.step)[1] == 30, 15)
    # a check-engine job running too: the preferences show it
    check = jobs.start("check_engine", bridge.EngineProcess(fake_engine(tmp_path, "check", """
        emit("progress", stage="selftest", step=1, total=2)
        time.sleep(30)
    """), cwd=tmp_path), label="Engine check")
    assert wait_until(lambda: (jobs.drain(), check.stage)[1] == "selftest", 15)
    logs = _draw_all(extension, registered)
    main = logs["MOTIONSPLATS_PT_main"]
    # latest() is the newest running job: the check; the train job's box is drawn by draw_job
    job_log: list = []
    extension.panels.main_panel.draw_job(Layout(job_log), job)
    assert "Reconstruct: running" in labels(job_log)
    assert "Stage: train" in labels(job_log) and "ETA 1:15" in labels(job_log)
    assert any("loss 0.125" in t and "PSNR 22.50 dB" in t for t in labels(job_log))
    progress = [c for c in job_log if c[0] == "progress"]
    assert progress and progress[0][2]["factor"] == pytest.approx(0.3) and progress[0][2]["text"] == "30/100"
    assert ("set", "motion_splats.cancel_job", "job_id", job.id) in job_log
    assert "motion_splats.cancel_job" in operators(main)
    assert any(t.startswith("Engine check: selftest 1/2") for t in labels(logs["prefs"]))
    check.process.kill()
    jobs.wait(check, timeout=10)
    jobs.remove(check.id)  # the main panel shows the newest job: the train job again

    # cancel requested: "Stopping" shows until the engine exits
    job.process.cancel(timeout=5)
    stopping: list = []
    extension.panels.main_panel.draw_job(Layout(stopping), job)
    assert job.completed or any("Stopping" in t for t in labels(stopping)) or job.process.state == "cancelled"
    jobs.wait(job, timeout=10)
    assert job.state == "cancelled"
    logs = _draw_all(extension, registered)
    assert "Reconstruct: cancelled" in labels(logs["MOTIONSPLATS_PT_main"])

    # failed: the error box with the engine's message, no traceback
    bad = jobs.wait(jobs.start("train", bridge.EngineProcess(fake_engine(tmp_path, "bad", """
        emit("log", level="info", message="loading clip")
        emit("error", message="clip.json: no frames found", path="clip.json", fix="export the clip again")
        sys.exit(2)
    """), cwd=tmp_path), label="Reconstruct"), timeout=15)
    assert bad.state == "failed"
    logs = _draw_all(extension, registered)
    main = logs["MOTIONSPLATS_PT_main"]
    assert "Reconstruct: failed" in labels(main) and "The engine failed" in labels(main)
    assert any("no frames found" in t for t in labels(main))
    assert ("attr", "alert", True) in main
    assert not any("Traceback" in t for t in labels(main))
    assert labels(main) == labels(logs["MOTIONSPLATS_PT_clip_main"])

    # finished check job: versions in the preferences
    assert all(c.kind == "train" for c in jobs.all_jobs())
    ok = jobs.wait(jobs.start("check_engine", bridge.EngineProcess(fake_engine(tmp_path, "ok", """
        emit("result", engine="0.1", python="3.11.9", cuda=False, versions={"torch": "2.13.0", "numba": None},
             problems={"numba": "not installed"})
    """), cwd=tmp_path), label="Engine check"), timeout=15)
    assert ok.state == "finished"
    prefs = labels(draw(type(registered), owner=registered))
    assert "Engine OK" in prefs and "torch: 2.13.0" in prefs and "numba: missing" in prefs
    assert any("not installed" in t for t in prefs)


def test_panels_draw_with_result_built(extension, registered, tmp_path):
    from tests.addon.test_build_bundle import make_bundle

    make_bundle(tmp_path / "b", n=6, g=60)
    assert bpy.ops.motion_splats.import_bundle(directory=str(tmp_path / "b")) == {"FINISHED"}
    logs = _draw_all(extension, registered)
    res = logs["MOTIONSPLATS_PT_result"]
    assert not any(t.startswith("No result") for t in labels(res))
    assert {"motion_splats.set_preview", "motion_splats.send_edits", "motion_splats.finetune",
            "motion_splats.export_ply", "motion_splats.import_bundle"} <= set(operators(res))
    props = [c[1][1] for c in res if c[0] == "prop"]
    assert {"density", "preview", "with_rig", "finetune_steps"} <= set(props)
    # the import button carries the panel's build settings
    assert ("set", "motion_splats.import_bundle", "density", 1.0) in res
    assert "No engine job" in labels(logs["MOTIONSPLATS_PT_main"])


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX fake engine")
def test_panels_draw_after_file_load_with_job(extension, registered, tmp_path, clean_jobs):
    """A job survives loading another file; the panels still draw it (settings are fresh)."""
    jobs, bridge = clean_jobs, extension.addon.bridge
    job = jobs.start("train", bridge.EngineProcess(fake_engine(tmp_path, "slow", """
        emit("progress", stage="priors", step=1, total=4)
        time.sleep(30)
    """), cwd=tmp_path), label="Reconstruct")
    assert wait_until(lambda: (jobs.drain(), job.stage)[1] == "priors", 15)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    logs = _draw_all(extension, registered)
    assert "Stage: priors" in labels(logs["MOTIONSPLATS_PT_main"])
    job.process.kill()
    jobs.wait(job, timeout=10)


def test_job_box_is_honest_while_the_engine_is_quiet(extension, registered, tmp_path, clean_jobs):
    """Issue #18.5: a finished stage followed by silence is not 'ETA 0:00'; the box says
    the next stage is being prepared and shows the elapsed time and the last log lines."""
    jobs, bridge = extension.addon.jobs, extension.addon.bridge
    main_panel = extension.panels.main_panel
    job = jobs.start("train", bridge.EngineProcess(fake_engine(tmp_path, "quiet", """
        emit("log", level="info", message="MANI: 96 nodes")
        emit("progress", stage="nodes", step=1, total=1, eta_s=0.0)
        time.sleep(30)
    """), cwd=tmp_path), label="Reconstruct")
    assert wait_until(lambda: (jobs.drain(), job.stage)[1] == "nodes", 15)
    job.last_event -= 10  # ten quiet seconds since the stage finished
    box: list = []
    main_panel.draw_job(Layout(box), job)
    texts = labels(box)
    assert not any(t.startswith("ETA") for t in texts), texts
    assert any(t.startswith("Preparing the next stage") for t in texts), texts
    assert any(t.startswith("Elapsed ") for t in texts)
    assert any("MANI: 96 nodes" in t for t in texts)
    # a stage under way with a real estimate shows it
    job.apply({"event": "progress", "stage": "train", "step": 30, "total": 100, "eta_s": 75})
    box = []
    main_panel.draw_job(Layout(box), job)
    assert "ETA 1:15" in labels(box)
    job.process.kill()
    jobs.wait(job, timeout=10)


def test_job_box_shows_the_engines_compile_stage(extension, registered, tmp_path, clean_jobs):
    """Issue #18.5: the engine reports loading / compiling its kernels as the stage
    ``compile`` (engine/train/warmup.py); the box names it, says what a first run costs,
    shows the engine's measured ETA counting down, and the engine's log line after it."""
    jobs, bridge = extension.addon.jobs, extension.addon.bridge
    main_panel = extension.panels.main_panel
    job = jobs.start("train", bridge.EngineProcess(fake_engine(tmp_path, "compiling", """
        emit("progress", stage="nodes", step=1, total=1, eta_s=0.0)
        emit("progress", stage="compile", step=0, total=5)
        emit("progress", stage="compile", step=2, total=5, eta_s=30.0)
        time.sleep(30)
    """), cwd=tmp_path), label="Reconstruct")
    assert wait_until(lambda: (jobs.drain(), job.step)[1] == 2, 15)
    box: list = []
    main_panel.draw_job(Layout(box), job)
    texts = labels(box)
    assert "Stage: compiling the engine's kernels" in texts, texts
    assert any("first run compiles them" in t for t in texts), texts
    assert not any(t.startswith("Preparing the next stage") for t in texts), texts
    assert "ETA 0:30" in texts, texts
    # the ETA counts down from when it arrived, and is never shown as 0:00
    job.progress_at -= 12
    assert "ETA 0:18" in main_panel.progress_lines(job, job.progress_at + 12)
    assert not any(t.startswith("ETA") for t in main_panel.progress_lines(job, job.progress_at + 31))
    job.apply({"event": "progress", "stage": "compile", "step": 5, "total": 5, "eta_s": 0.0})
    job.apply({"event": "log", "level": "info", "message": "engine kernels compiled (40 compilations) in 41.0 s"})
    box = []
    main_panel.draw_job(Layout(box), job)
    texts = labels(box)
    assert not any(t.startswith("ETA") for t in texts), texts
    assert any("engine kernels compiled" in t for t in texts), texts
    job.process.kill()
    jobs.wait(job, timeout=10)
