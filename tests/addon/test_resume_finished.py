"""Issue #22.4 (add-on): Resume is off for a finished bundle. Its poll returns False with the
reason (``engine.bundle.finished_steps``: no checkpoint left and ``stats.steps`` reached
``config.steps``), and calling it anyway starts no engine."""

from __future__ import annotations

import json

import pytest

from tests.addon._support import bpy, clean_jobs, registered, user_dir  # noqa: F401


def _bundle(path, steps, target, checkpoint=False):
    path.mkdir(parents=True)
    (path / "scene.json").write_text(json.dumps({"stage": "train", "stats": {"steps": steps},
                                                 "config": {"steps": target}}), encoding="utf-8")
    if checkpoint:
        (path / "checkpoints").mkdir()
        (path / "checkpoints" / "checkpoint.pt").write_bytes(b"x")


def test_resume_is_off_for_a_finished_bundle(extension, registered, tmp_path, clean_jobs):
    s = bpy.context.scene.motion_splats_result
    clip = tmp_path / "clip"
    clip.mkdir()
    s.last_clip = str(clip)
    registered.engine_python = str(tmp_path / "never_run_python")
    # an interrupted run (a checkpoint, steps short of the target) is resumable
    _bundle(tmp_path / "cancelled", 40, 100, checkpoint=True)
    s.bundle_path = str(tmp_path / "cancelled")
    assert bpy.ops.motion_splats.resume.poll()
    # a finished run is not: poll says why, and calling it anyway is refused too
    _bundle(tmp_path / "done", 100, 100)
    s.bundle_path = str(tmp_path / "done")
    assert not bpy.ops.motion_splats.resume.poll()
    with pytest.raises(RuntimeError, match=r"finished \(100 steps\): nothing to resume"):
        bpy.ops.motion_splats.resume()
    ops = extension.operators.reconstruct_ops
    assert ops.finished_run(str(tmp_path / "done")) == 100
    op = type("Op", (), {"reports": [], "report": lambda self, kind, msg: self.reports.append(msg)})()
    assert ops.start_training(op, bpy.context, resume=True) == {"CANCELLED"}
    assert "nothing to resume" in op.reports[-1]
    assert clean_jobs.latest("train") is None  # no engine was started
    # the bundle changes (trained again with a checkpoint): Resume is offered again
    (tmp_path / "done" / "checkpoints").mkdir()
    (tmp_path / "done" / "checkpoints" / "checkpoint.pt").write_bytes(b"x")
    assert bpy.ops.motion_splats.resume.poll()
