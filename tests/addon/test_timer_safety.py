"""Issue #18.8: what the job timer does to the scene is safe. A finished reconstruction builds
only into the scene it was started from (not whatever file is open now), never switches the
artist out of Edit Mode, and dynamic enum items keep their strings alive."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import bpy

from tests.addon._support import clean_jobs, registered, user_dir  # noqa: F401
from tests.addon.test_build_bundle import make_bundle


def _fake_engine(tmp_path, bundle: Path) -> Path:
    """An interpreter that 'trains' at once: one result event naming ``bundle``."""
    fake = tmp_path / "fake_python"
    fake.write_text(f"#!{sys.executable}\n" + textwrap.dedent(f"""
        import json, sys, time
        print(json.dumps({{"v": 1, "event": "result", "time": time.time(), "bundle": {str(bundle)!r}}}), flush=True)
        """), encoding="utf-8")
    fake.chmod(0o755)
    return fake


def _start(registered, tmp_path):
    bundle = tmp_path / "bundle"
    make_bundle(bundle, n=6, g=60)
    registered.engine_python = str(_fake_engine(tmp_path, bundle))
    registered.results_dir = str(tmp_path / "results")
    footage = tmp_path / "capture"
    (footage / "camera").mkdir(parents=True)
    (footage / "dataset.json").write_text("{}", encoding="utf-8")
    bpy.context.scene.motion_splats_result.clip_path = str(footage)
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}


def _built():
    return [c for c in bpy.data.collections if "ms_bundle" in c]


def test_result_never_lands_in_another_file(registered, tmp_path, clean_jobs):
    _start(registered, tmp_path)
    job = clean_jobs.latest("train")
    bpy.ops.wm.read_factory_settings(use_empty=True)  # the artist opened another file (also called "Scene")
    clean_jobs.wait(job, 30)
    assert job.state == "finished"
    assert not _built(), "the result was built into an unrelated scene"
    assert "no longer open" in (job.callback_error or "") and str(tmp_path / "bundle") in job.callback_error


def test_result_waits_for_object_mode(registered, tmp_path, clean_jobs):
    scene = bpy.context.scene
    mesh = bpy.data.meshes.new("m")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    obj = bpy.data.objects.new("m", mesh)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    _start(registered, tmp_path)
    job = clean_jobs.latest("train")
    clean_jobs.wait(job, 30)
    assert job.completed and not _built()
    assert bpy.context.mode == "EDIT_MESH" and bpy.context.view_layer.objects.active == obj  # left alone
    assert any("Object Mode" in line for line in job.logs)
    bpy.ops.object.mode_set(mode="OBJECT")
    clean_jobs.drain()
    assert len(_built()) == 1 and job.callback_error is None, job.callback_error
    assert job.pending is None


def test_dynamic_enum_items_keep_their_strings(extension, registered, tmp_path):
    items = extension.operators.result_ops._clip_items
    img = bpy.data.images.new("f", 8, 8)
    img.filepath_raw = str(tmp_path / "f_0001.png")
    img.file_format = "PNG"
    img.save()
    bpy.data.movieclips.load(str(tmp_path / "f_0001.png"))
    first, second = items(None, bpy.context), items(None, bpy.context)
    assert first[0][0] == "f_0001.png"
    assert first[0][0] is second[0][0]  # the same, still referenced string objects
