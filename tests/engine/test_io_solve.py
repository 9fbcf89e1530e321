"""Camera solve (pycolmap) on a synthetic textured room, Umeyama, and the real sample clips."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_io_scene import Room, orbit_cameras  # noqa: E402

from engine.errors import InputError  # noqa: E402
from engine.io import solve_select as sel  # noqa: E402
from engine.io import load_clip  # noqa: E402
from engine.io.clip import Clip, FrameSource, times_from_count  # noqa: E402
from engine.io.solve import default_K as solve_default_K  # noqa: E402
from engine.io.solve import interpolate_poses, solve_cameras, umeyama_similarity  # noqa: E402

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "clips"


def test_umeyama_recovers_similarity():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    R = Rotation.random(random_state=1).as_matrix()
    dst = 2.5 * src @ R.T + [1.0, -2.0, 3.0]
    s, R2, t = umeyama_similarity(src, dst)
    assert abs(s - 2.5) < 1e-10 and np.allclose(R2, R) and np.allclose(t, [1, -2, 3])
    s1, _, _ = umeyama_similarity(src, dst, with_scale=False)
    assert s1 == 1.0


def test_interpolate_poses_fills_gaps():
    from scipy.spatial.transform import Rotation

    w2c = np.tile(np.eye(4), (5, 1, 1))
    Rs = Rotation.from_rotvec([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0.4, 0]]).as_matrix()
    w2c[:, :3, :3] = Rs
    w2c[0, :3, 3] = [0, 0, 0]
    w2c[4, :3, 3] = -Rs[4] @ np.array([4.0, 0, 0])
    reg = np.array([True, False, False, False, True])
    out = interpolate_poses(w2c, reg, np.linspace(0, 1, 5))
    C = -np.einsum("fji,fj->fi", out[:, :3, :3], out[:, :3, 3])
    np.testing.assert_allclose(C[:, 0], [0, 1, 2, 3, 4], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(out[2, :3, :3]).as_rotvec(), [0, 0.2, 0], atol=1e-12)


def synthetic_clip(tmp_path, n=16, W=320, H=240):
    f = 260.0 * W / 320  # same field of view at every size
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    w2c = orbit_cameras(n)
    return _clip_from(tmp_path, K, w2c, W, H), K, w2c


def test_solve_synthetic_room(tmp_path):
    clip, K, w2c = synthetic_clip(tmp_path)
    # a "dynamic" blob in the middle of every frame: masked out of feature extraction
    masks = [np.zeros((240, 320), np.float32) for _ in range(clip.num_frames)]
    for m in masks:
        m[100:140, 140:180] = 1.0
    out = solve_cameras(clip, masks=masks, max_size=240, max_features=1500)
    info = out.meta["solve"]
    assert info["num_registered"] >= 14 and info["mean_reproj_error"] < 1.0
    assert out.K.shape == (16, 3, 3) and out.w2c.shape == (16, 4, 4)
    # intrinsics scaled back to full resolution
    assert abs(out.K[0, 0, 0] - 260.0) / 260.0 < 0.03
    assert abs(out.K[0, 0, 2] - 160.0) < 1.0 and abs(out.K[0, 1, 2] - 120.0) < 1.0
    Cs = out.camera_centers()
    Cg = -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])
    s, R, t = umeyama_similarity(Cs, Cg)
    err = np.linalg.norm(s * Cs @ R.T + t - Cg, axis=1).mean()
    extent = np.linalg.norm(Cg.max(0) - Cg.min(0))
    assert err <= 0.02 * extent
    # orientations agree too (after the similarity's rotation)
    Rw = out.w2c[:, :3, :3] @ R.T
    ang = np.degrees(np.arccos(np.clip((np.einsum("fij,fij->f", Rw, w2c[:, :3, :3]) - 1) / 2, -1, 1)))
    assert ang.max() < 1.0
    assert out.points is not None and len(out.points) > 100


def test_solve_static_camera_fails_clearly(tmp_path):
    clip, K, w2c = synthetic_clip(tmp_path, n=6, W=160, H=120)
    static = clip.subset([0, 0, 0, 0, 0, 0])
    with pytest.raises(InputError, match="registered") as e:
        solve_cameras(static, max_features=500)
    assert "Supply cameras" in e.value.fix


# ----------------------------------------------------------------------------------
# Low-parallax fallback (fixed camera centre) and the real sample clips
# ----------------------------------------------------------------------------------
class _Log:
    def __init__(self):
        self.messages = []

    def log(self, message, level="info"):
        self.messages.append((level, message))

    def progress(self, *a, **k):
        pass


def _clip_from(tmp_path, K, w2c, W, H):
    room = Room()
    paths = []
    for i, M in enumerate(w2c):
        p = tmp_path / f"{i:03d}.png"
        cv2.imwrite(str(p), room.render(K, M, W, H)[:, :, ::-1])
        paths.append(p)
    return Clip(frames=FrameSource(paths=paths), width=W, height=H, fps=24.0, times=times_from_count(len(paths)),
                frame_ids=[p.name for p in paths], source=tmp_path)


def test_static_camera_falls_back_with_warning(tmp_path):
    clip, K, w2c = synthetic_clip(tmp_path, n=6, W=160, H=120)
    static = clip.subset([0, 0, 0, 0, 0, 0])
    rep = _Log()
    out = solve_cameras(static, max_features=500, static_fallback=True, fov_deg=70.0, reporter=rep)
    info = out.meta["solve"]
    assert info["model"] == "static" and info["num_registered"] == 6 and info["num_points"] == 0
    np.testing.assert_allclose(out.w2c, np.tile(np.eye(4), (6, 1, 1)))
    f = 80.0 / np.tan(np.radians(35.0))  # 70 degrees across the 160-px long side
    np.testing.assert_allclose(out.K[:, 0, 0], f)
    np.testing.assert_allclose(out.K[:, :2, 2], [[80, 60]] * 6)
    warn = [m for lvl, m in rep.messages if lvl == "warning"]
    assert len(warn) == 1 and "static camera" in warn[0] and "--fov" in warn[0] and "70 degree" in warn[0]
    assert np.isfinite(out.w2c).all() and out.scene_scale == 1.0


def test_rotating_camera_recovers_rotations(tmp_path):
    from scipy.spatial.transform import Rotation

    W, H, n = 200, 150, 8
    K = solve_default_K(W, H, 60.0)
    C = np.array([0.3, 0.2, -0.5])
    Rs = Rotation.from_euler("yx", np.c_[np.linspace(0, 6, n), np.linspace(0, 2, n)], degrees=True).as_matrix()
    w2c = np.tile(np.eye(4), (n, 1, 1))
    w2c[:, :3, :3] = Rs
    w2c[:, :3, 3] = -np.einsum("fij,j->fi", Rs, C)
    clip = _clip_from(tmp_path, K, w2c, W, H)
    rep = _Log()
    out = solve_cameras(clip, max_features=500, static_fallback=True, fov_deg=60.0, reporter=rep)
    info = out.meta["solve"]
    assert info["model"] == "rotation" and info["num_registered"] == n
    assert info["mean_reproj_error"] < 0.5
    # relative to frame 0 (the solved world axes), within a tenth of a degree
    Rrel = np.einsum("fij,kj->fik", w2c[:, :3, :3], w2c[0, :3, :3])
    d = np.einsum("fij,fkj->fik", out.w2c[:, :3, :3], Rrel)
    ang = np.degrees(np.arccos(np.clip((np.trace(d, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert ang.max() < 0.1
    np.testing.assert_allclose(out.camera_centers(), 0.0, atol=1e-12)
    assert any("rotates" in m for lvl, m in rep.messages if lvl == "warning")


def test_parallax_clip_still_solves_with_fallback_enabled(tmp_path):
    clip, K, w2c = synthetic_clip(tmp_path, n=12, W=240, H=180)
    out = solve_cameras(clip, max_size=240, max_features=1500, static_fallback=True, auto_masks=True)
    info = out.meta["solve"]
    assert info["model"] == "sfm" and info["num_registered"] >= 11 and info["mean_reproj_error"] < 1.0
    assert info["num_points"] > 100


@pytest.mark.needs_shared
@pytest.mark.skipif(not SHARED.is_dir(), reason="shared sample clips not present")
def test_real_clips_pan_solves_and_near_static_falls_back():
    """bedroom.mp4 (handheld pan, two children): parallax grows with the frame gap, global SfM registers the
    frames with sub-pixel error; cups.mp4 (near-static camera, hands): no parallax on the static matches ->
    the fixed-centre model by evidence, announced in one warning line."""
    opts = dict(max_size=320, auto_masks=True, global_retry=True, static_fallback=True, num_threads=1)  # 1: reproducible
    rep = _Log()
    bed = solve_cameras(load_clip(SHARED / "bedroom.mp4", frame_step=3, max_frames=40), reporter=rep, **opts)
    info = bed.meta["solve"]
    assert info["model"] == "sfm" and info["num_registered"] >= 36, info  # measured 40/40, 0.54 px, 60 points
    assert info["mean_reproj_error"] < 1.0 and info["num_points"] >= 10
    assert not any(lvl == "warning" for lvl, _ in rep.messages)
    chosen = [m for _, m in rep.messages if "chosen because" in m]
    assert len(chosen) == 1 and chosen[0].startswith("camera solve: translating camera"), rep.messages
    assert info["parallax_px"] >= sel.MIN_PARALLAX_PX and "reason" in info
    rep = _Log()
    cups = solve_cameras(load_clip(SHARED / "cups.mp4", frame_step=12, max_frames=25), reporter=rep, **opts)
    info = cups.meta["solve"]
    assert info["model"] in ("static", "rotation") and info["num_registered"] >= 20, info
    assert info["mean_reproj_error"] < 1.5  # transfer error of the fixed-centre model, full-res px
    assert np.isfinite(cups.w2c).all() and np.allclose(cups.camera_centers(), 0.0, atol=1e-9)
    chosen = [(lvl, m) for lvl, m in rep.messages if "chosen because" in m]
    assert len(chosen) == 1 and chosen[0][0] == "warning" and "--fov" in chosen[0][1], rep.messages
    assert info["parallax_px"] < sel.MIN_PARALLAX_PX  # no parallax: chosen by evidence, SfM not run


def test_textureless_clip_fails_clearly_even_with_fallback(tmp_path):
    paths = []
    rng = np.random.default_rng(0)
    for i in range(5):
        p = tmp_path / f"{i:03d}.png"
        cv2.imwrite(str(p), np.full((90, 120, 3), 128, np.uint8) + rng.integers(0, 2, (90, 120, 3), dtype=np.uint8))
        paths.append(p)
    clip = Clip(frames=FrameSource(paths=paths), width=120, height=90, fps=24.0, times=times_from_count(5),
                frame_ids=[p.name for p in paths], source=tmp_path)
    with pytest.raises(InputError, match="does not fit") as e:
        solve_cameras(clip, max_features=200, static_fallback=True, auto_masks=True, global_retry=True)
    assert "Supply cameras" in e.value.fix and e.value.path
