"""Engine operators end to end: check engine, cancel, create env (refused offline),
detect interpreter; the job registry and the sidebar panel; register/unregister twice."""

from __future__ import annotations

import sys

import bpy
import pytest

from tests.addon._support import (VENV_PYTHON, clean_jobs, fake_engine, registered,  # noqa: F401 (fixtures)
                                  user_dir, wait_until)

pytestmark = pytest.mark.timeout(180)


@pytest.mark.skipif(not VENV_PYTHON.is_file(), reason="no engine venv")
def test_check_engine_end_to_end(extension, registered):
    jobs = extension.addon.jobs
    registered.engine_python = str(VENV_PYTHON)
    assert bpy.ops.motion_splats.check_engine.poll()
    assert bpy.ops.motion_splats.check_engine() == {"FINISHED"}
    job = jobs.latest("check_engine")
    assert job is not None and job.running
    assert not bpy.ops.motion_splats.check_engine.poll()  # one check at a time
    assert bpy.app.timers.is_registered(jobs._timer)
    jobs.wait(job, timeout=120)  # timers do not fire headless: pump the drain function
    assert job.state == "finished", job.error_summary()
    assert job.result["ok"] is True and job.result["versions"]["torch"]
    assert job.error_summary() == []
    assert jobs._timer() is None  # nothing left to pump: the timer stops itself


def test_check_engine_bad_interpreter(extension, registered, tmp_path):
    jobs = extension.addon.jobs
    registered.engine_python = str(tmp_path / "nope" / "python")
    with pytest.raises(RuntimeError, match="Preferences"):
        bpy.ops.motion_splats.check_engine()
    job = jobs.latest("check_engine")
    assert job.state == "failed" and job.completed


def test_job_progress_cancel_and_callback(extension, registered, tmp_path):
    jobs, bridge = extension.addon.jobs, extension.addon.bridge
    argv = fake_engine(tmp_path, "train", """
        try:
            emit("progress", stage="train", step=5, total=50, loss=0.25, psnr=21.5, eta_s=90)
            while True:
                time.sleep(0.05)
        except KeyboardInterrupt:
            emit("error", message="interrupted", fix="re-run with --resume")
            sys.exit(130)
    """)
    seen = []
    job = jobs.start("train", bridge.EngineProcess(argv, cwd=tmp_path), label="Training", on_complete=seen.append)
    assert wait_until(lambda: (jobs.drain(), job.step)[1] == 5, 15)
    assert (job.stage, job.total, job.loss, job.psnr, job.eta_s) == ("train", 50, 0.25, 21.5, 90.0)
    assert job.factor == pytest.approx(0.1)
    # the panel draws the running job (stub layout: headless has no regions)
    _draw_panel(extension)
    # survives a file load: the registry is not in bpy.data
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert jobs.get(job.id) is job and job.running
    assert bpy.ops.motion_splats.cancel_job.poll()
    assert bpy.ops.motion_splats.cancel_job(job_id=job.id) == {"FINISHED"}
    jobs.wait(job, timeout=10)
    assert job.state == "cancelled" and seen == [job]
    assert not bpy.ops.motion_splats.cancel_job.poll()
    _draw_panel(extension)


def test_failed_job_and_callback_errors_are_shown(extension, registered, tmp_path):
    jobs, bridge = extension.addon.jobs, extension.addon.bridge
    argv = fake_engine(tmp_path, "boom", """
        emit("result", bundle="x")
    """)

    def broken(job):
        raise ValueError("builder bug")

    job = jobs.wait(jobs.start("train", bridge.EngineProcess(argv, cwd=tmp_path), on_complete=broken))
    assert job.state == "finished"
    assert job.error_summary() == ["Building the result failed: ValueError: builder bug"]
    argv = fake_engine(tmp_path, "crash", "raise SystemExit('fatal: disk full')\n")
    job = jobs.wait(jobs.start("train", bridge.EngineProcess(argv, cwd=tmp_path)))
    assert job.state == "failed" and "fatal: disk full" in " ".join(job.error_summary())
    _draw_panel(extension)


def test_create_env_refused_offline(extension, registered):
    assert bpy.app.online_access is False  # headless bpy default
    with pytest.raises(RuntimeError, match="Online access"):
        bpy.ops.motion_splats.create_engine_env()
    assert extension.addon.jobs.latest("env_setup") is None


def test_detect_interpreter(extension, registered, user_dir):
    assert registered.engine_python == ""
    assert bpy.ops.motion_splats.detect_interpreter() == {"FINISHED"}
    assert registered.engine_python == extension.addon.preferences.interpreter_candidates()[0]


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX stub interpreter")
def test_env_setup_script_reports_errors(extension, tmp_path):
    """The setup script speaks the protocol; a failing pip yields an error event.

    The "venv" already exists and its python is a stub that fails, so nothing is
    downloaded and no real environment is touched."""
    env_setup, bridge = extension.addon.env_setup, extension.addon.bridge
    py = env_setup.venv_python(tmp_path / "venv")
    py.parent.mkdir(parents=True)
    py.write_text("#!/bin/sh\necho 'ERROR: no network' >&2\nexit 3\n")
    py.chmod(0o755)
    argv = env_setup.setup_command(sys.executable, tmp_path / "venv")
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    events = []
    proc.wait(60)
    events = proc.poll_events()
    assert proc.state == "failed"
    assert [e["stage"] for e in events if e["event"] == "progress"] == ["pip", "install"]
    assert any("no network" in e.get("message", "") for e in events if e["event"] == "log")
    assert "pip could not install" in proc.error_summary()[0]


def test_register_unregister_twice_with_jobs_module(extension, empty_scene):
    jobs = extension.addon.jobs
    for _ in range(2):
        extension.register()
        assert jobs._on_load_post in bpy.app.handlers.load_post
        for cls in extension.operators.engine_ops.CLASSES + extension.panels.main_panel.CLASSES:
            assert cls.is_registered
        extension.unregister()
        assert jobs._on_load_post not in bpy.app.handlers.load_post
        assert not bpy.app.timers.is_registered(jobs._timer)
        assert not extension.addon.preferences.MotionSplatsPreferences.is_registered


class _Stub:
    """A layout stand-in that accepts every call (headless bpy has no UI regions)."""

    def __getattr__(self, name):
        return lambda *a, **k: _Stub()

    def __setattr__(self, name, value):
        pass


def _draw_panel(extension):
    panel = type("P", (), {"layout": _Stub()})()
    extension.panels.main_panel.MOTIONSPLATS_PT_main.draw(panel, bpy.context)
