"""Fine-tune Appearance: edit a node F-curve, the operator sends the edit and runs a real
``python -m engine finetune`` job on a tiny trained bundle; the bundle's motion is the
edited one (unchanged by the engine), appearance changes, the preview is rebuilt and the
edited Empties are kept."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.addon._support import fcurves_of, REPO, VENV_PYTHON, bpy, clean_jobs, registered, user_dir  # noqa: F401

pytestmark = pytest.mark.skipif(not VENV_PYTHON.exists(), reason="needs the engine venv")


@pytest.fixture(scope="module")
def trained_bundle(tmp_path_factory):
    """A 5-step bundle of the tiny synthetic clip (engine subprocesses; no Blender state)."""
    root = tmp_path_factory.mktemp("ft")
    code = ("import sys; sys.path.insert(0, sys.argv[1]); from tools.synth_scene import generate_scene; "
            "generate_scene(sys.argv[2], preset='tiny')")
    subprocess.run([str(VENV_PYTHON), "-c", code, str(REPO), str(root / "clip")], check=True, cwd=str(REPO),
                   capture_output=True, timeout=300)
    out = root / "bundle"
    r = subprocess.run([str(VENV_PYTHON), "-m", "engine", "train", str(root / "clip"), "--out", str(out), "--steps",
                        "5", "--jsonl"], cwd=str(REPO), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return out


def _pump_until(jobs, predicate, timeout):
    from tests.addon._support import wait_until

    return wait_until(lambda: (jobs.drain(), predicate())[1], timeout, step=0.05)


def test_finetune_operator_real_engine(extension, registered, tmp_path, trained_bundle, clean_jobs):
    import shutil

    from engine import bundle as bio

    jobs = clean_jobs
    bdir = tmp_path / "bundle"
    shutil.copytree(trained_bundle, bdir, ignore=shutil.ignore_patterns("cache", "checkpoints", "report"))
    registered.engine_python = str(VENV_PYTHON)
    registered.cache_dir = str(tmp_path / "cache")
    registered.device = "CPU"
    before = bio.load_bundle(bdir)
    assert not bpy.ops.motion_splats.finetune.poll()  # nothing built yet
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir)) == {"FINISHED"}
    build = extension.addon.build
    col = build.bundle_collection(bpy.context)
    empties = build.node_empties(col)

    # the artist's edit: node 0's z key 1 (value and both handles) up by 0.1
    fcs = fcurves_of(empties[0])
    kp = fcs.find("location", index=2).keyframe_points[1]
    for attr in ("co", "handle_left", "handle_right"):
        v = getattr(kp, attr)
        setattr(kp, attr, (v[0], v[1] + 0.1))
    edited_z = kp.co[1]

    bpy.context.scene.motion_splats_result.finetune_steps = 6
    assert bpy.ops.motion_splats.finetune.poll()
    assert bpy.ops.motion_splats.finetune() == {"FINISHED"}
    job = jobs.latest("finetune")
    assert job is not None and job.label == "Fine-tune"
    argv = job.process.argv
    assert argv[argv.index("finetune") + 1:] == ["--jsonl", str(bdir.resolve()), "--steps", "6", "--device", "cpu"] \
        or argv[-4:] == ["--steps", "6", "--device", "cpu"], argv
    assert not bpy.ops.motion_splats.finetune.poll() or job.completed  # one writer at a time
    assert not bpy.ops.motion_splats.resume.poll() or job.completed
    # the edit reached the bundle before the engine started
    sent = bio.read_nodes(bdir / bio.NODES_FILE)
    assert sent.pos_keys[0, 1, 2] == pytest.approx(before.nodes.pos_keys[0, 1, 2] + 0.1, abs=1e-5)
    sent_bytes = (bdir / bio.NODES_FILE).read_bytes()

    assert _pump_until(jobs, lambda: job.completed, 300), f"still running: {job.stage} {job.step}"
    assert job.state == "finished", job.error_summary()
    assert job.callback_error is None, job.callback_error
    res = job.result
    assert res["steps"] == 6 and res["psnr_after"] >= res["psnr_before"]
    # motion: exactly the sent edit; the engine changed appearance only
    assert (bdir / bio.NODES_FILE).read_bytes() == sent_bytes
    after = bio.load_bundle(bdir)
    np.testing.assert_array_equal(after.gaussians.means, before.gaussians.means)
    assert not np.array_equal(after.gaussians.sh, before.gaussians.sh)
    assert (Path(res["backup"]) / bio.GAUSSIANS_FILE).is_file()
    assert json.loads((bdir / bio.SCENE_FILE).read_text())["stats"]["finetune"][-1]["steps"] == 6

    # the preview was rebuilt from the new appearance; the edited Empties are the same objects
    col = build.bundle_collection(bpy.context)
    assert build.node_empties(col) == empties
    kp = fcurves_of(empties[0]).find(
        "location", index=2).keyframe_points[1]
    assert kp.co[1] == pytest.approx(edited_z)
    mesh = next(o for o in col.objects if "ms_gaussians" in o)
    n = len(mesh.data.vertices)
    cols = np.zeros(n * 4, np.float32)
    mesh.data.attributes["ms_color"].data.foreach_get("color", cols)
    idx = np.zeros(n, np.int32)
    mesh.data.attributes["ms_index"].data.foreach_get("value", idx)
    want = build.srgb_to_linear(after.gaussians.colors[idx])
    np.testing.assert_allclose(cols.reshape(n, 4)[:, :3], want, atol=1e-4)


def test_finetune_args(extension):
    ops = extension.operators.finetune_ops
    assert ops.finetune_args("/b", 7) == ["/b", "--steps", "7"]
    assert ops.finetune_args("/b", 0, "cpu") == ["/b", "--steps", "1", "--device", "cpu"]
