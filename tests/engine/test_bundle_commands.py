"""`render` and `export` on a trained bundle; a reloaded bundle moves like the trainer."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from engine import bundle as B
from engine.train.config import preset_config
from engine.train.from_bundle import model_from_bundle
from engine.train.trainer import Trainer

from .synthetic_training import make_nodes, make_scene

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    data, truth = make_scene(frames=8)
    cfg = preset_config("preview", steps=30, gaussians_per_frame=500, init_keyframes=3, num_nodes=25,
                        densify_from=10, densify_until=25, densify_every=10, checkpoint_every=0)
    out = tmp_path_factory.mktemp("bundle") / "run"
    trainer = Trainer(data, make_nodes(truth), cfg, out)
    trainer.run()
    return trainer, out


def _engine(*args):
    return subprocess.run([sys.executable, "-m", "engine", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=300)


def test_reloaded_bundle_deforms_like_the_trainer(trained):
    trainer, out = trained
    model = model_from_bundle(B.load_bundle(out))
    for t in (0.0, 0.37, 1.0):
        with torch.no_grad():
            a, qa = trainer.model.deform(t)
            b, qb = model.deform(t)
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(qa.abs(), qb.abs(), atol=1e-5, rtol=1e-5)


def test_render_command_writes_frames(trained, tmp_path):
    _, out = trained
    res = _engine("render", out, "--frames", "1-3", "--out", tmp_path / "r", "--jsonl")
    assert res.returncode == 0, res.stderr
    files = sorted((tmp_path / "r").glob("*.png"))
    assert [f.name for f in files] == ["frame_00001.png", "frame_00002.png", "frame_00003.png"]
    # refuses to overwrite earlier results
    again = _engine("render", out, "--frames", "1", "--out", tmp_path / "r")
    assert again.returncode == 2 and "--overwrite" in again.stderr


def test_render_from_blender_camera_path(trained, tmp_path):
    _, out = trained
    scene = B.load_bundle(out).scene
    cam = scene["cameras"][0]
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"format": "motion-splats-camera-path", "version": 1, "cameras": [
        {"frame": 2, "K": cam["K"], "w2c": cam["w2c"], "width": 40, "height": 30}]}))
    res = _engine("render", out, "--camera", path, "--out", tmp_path / "p")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "p" / "frame_00002.png").is_file()
    path.write_text('{"format": "motion-splats-camera-path", "cameras": [{"frame": 1}]}')
    bad = _engine("render", out, "--camera", path, "--out", tmp_path / "q")
    assert bad.returncode == 2 and "path.json" in bad.stderr


def test_export_ply_sequence_matches_deformation(trained, tmp_path):
    trainer, out = trained
    res = _engine("export", out, "--ply-sequence", tmp_path / "seq", "--frames", "1,8", "--ply", tmp_path / "c.ply")
    assert res.returncode == 0, res.stderr
    last = B.read_ply(tmp_path / "seq" / "frame_00008.ply")
    with torch.no_grad():
        means, _ = trainer.model.deform(1.0)
    np.testing.assert_allclose(last.means, means.numpy(), atol=1e-5)
    assert B.read_ply(tmp_path / "c.ply").count == last.count


def test_ply_sequence_keeps_the_shot_detail_only_as_its_own_camera_sees_it(trained, tmp_path):
    """A PLY has no view-dependent opacity: the view-bound Gaussians (shot detail) are left out
    of a frame's PLY (opacity ~0), and with --shot-camera kept at what frame 1's own camera sees."""
    trainer, out = trained
    m = trainer.model
    bound = (m.gauss_view_angle > 0).numpy()
    own = bound & (np.abs(m.gauss_t_center.numpy() - float(trainer.data.times[0])) < 1e-6)
    assert own.sum() > 10
    for flag, name in (((), "plain"), (("--shot-camera",), "shot")):
        res = _engine("export", out, "--ply-sequence", tmp_path / name, "--frames", "1", *flag)
        assert res.returncode == 0, res.stderr
    plain = B.read_ply(tmp_path / "plain" / "frame_00001.ply").opacities
    shot = B.read_ply(tmp_path / "shot" / "frame_00001.ply").opacities
    assert plain[bound].max() < 1e-6
    with torch.no_grad():
        want = m.opacities_at(float(trainer.data.times[0])).numpy()
    np.testing.assert_allclose(shot[own], want[own], rtol=1e-4)  # the own camera: no fade
    np.testing.assert_allclose(shot[~bound], plain[~bound], rtol=1e-6)


def test_bad_bundle_is_a_clear_error(tmp_path):
    res = _engine("render", tmp_path / "nope", "--out", tmp_path / "o")
    assert res.returncode == 2
    assert "nope" in res.stderr and "Traceback" not in res.stderr
