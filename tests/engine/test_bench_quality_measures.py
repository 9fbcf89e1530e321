"""The measures `engine.bench quality` adds for moving objects (issue #17): the still-plate
baseline, node trajectories after training vs ground truth, paired statistics."""

from __future__ import annotations

import numpy as np
import pytest

from engine.bench.node_motion import trajectory_error
from engine.bench.quality import paired_stats
from engine.bench.still_plate import still_plate, still_plate_scores
from engine.bundle import NodeArrays


def _textured(h=48, w=64, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _moving_square(frames=12, h=48, w=64, size=10):
    """A textured static background with a white square sliding left to right."""
    bg = _textured(h, w)
    imgs, masks = [], []
    for f in range(frames):
        x = int(round(f * (w - size) / (frames - 1)))
        img, m = bg.copy(), np.zeros((h, w), bool)
        img[18:18 + size, x:x + size] = 255
        m[18:18 + size, x:x + size] = True
        imgs.append(img)
        masks.append(m)
    return np.stack(imgs), np.stack(masks), bg


def test_still_plate_of_a_static_clip_is_the_frame_and_scores_perfect():
    frames = np.stack([_textured()] * 5)
    assert np.array_equal(still_plate(frames), frames[0])
    s = still_plate_scores(frames)
    assert s["plate_psnr"] >= 119.0 and s["plate_masked_psnr"] is None and s["frames"] == 5


def test_still_plate_recovers_the_background_and_fails_on_the_moving_region():
    frames, masks, bg = _moving_square()
    # the square covers each pixel in at most 2 of 12 frames: the median is the background
    assert np.array_equal(still_plate(frames), bg)
    s = still_plate_scores(frames, masks)
    # inside the mask the plate shows the background where the frame shows white: bad; the
    # whole image differs only there, so it scores 10·log10(area ratio) higher
    assert s["plate_masked_psnr"] < 10.0
    assert s["plate_psnr"] == pytest.approx(s["plate_masked_psnr"] + 10 * np.log10(48 * 64 / 100), abs=0.5)
    expect = np.mean([-10 * np.log10((((255 - bg.astype(float)) / 255) ** 2)[m].mean()) for m in masks])
    assert s["plate_masked_psnr"] == pytest.approx(expect, rel=1e-9)


def test_still_plate_refuses_mismatched_masks():
    frames, masks, _ = _moving_square()
    with pytest.raises(ValueError, match="masks"):
        still_plate_scores(frames, masks[:, :10])


def _scene(frames=9, seed=0):
    """GT: a static slab and a moving blob (translation + a little rotation over time)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, frames).astype(np.float32)
    static = np.concatenate([rng.uniform(-2, 2, (300, 2)), np.full((300, 1), -2.0)], 1)  # far below the blob
    blob = rng.normal(0, 0.15, (200, 3)) + [0, 0, 0.5]
    path = np.stack([1.5 * np.sin(np.pi * t), 0.8 * t, 0.1 * t], 1)  # (F, 3)
    pts = np.concatenate([np.repeat(static[:, None], frames, 1), blob[:, None] + path[None]], 0)
    dyn = np.r_[np.zeros(300, bool), np.ones(200, bool)]
    return pts.astype(np.float32), t, dyn, path


def _nodes(centres, path_per_node, key_times):
    """NodeArrays whose splines pass through ``path_per_node`` (N, K, 3) at ``key_times``."""
    from engine.geometry.hermite import catmull_rom_tangents
    import torch

    kt = torch.as_tensor(key_times)
    keys = torch.as_tensor(path_per_node, dtype=torch.float32)
    tan = catmull_rom_tangents(kt, keys).numpy()
    n, k = keys.shape[:2]
    quat = np.zeros((n, k, 4), np.float32)
    quat[..., 0] = 1
    return NodeArrays(centers=centres.astype(np.float32), radii=np.full(n, 0.3, np.float32), key_times=key_times,
                      pos_keys=keys.numpy(), pos_tangents=tan.astype(np.float32), rot_keys=quat,
                      rot_tangents=np.zeros_like(quat))


def test_nodes_moved_along_the_ground_truth_score_near_zero_and_frozen_nodes_score_zero_motion():
    pts, t, dyn, path = _scene()
    rng = np.random.default_rng(1)
    stat_c = np.concatenate([rng.uniform(-2, 2, (40, 2)), np.full((40, 1), -2.0)], 1)
    blob_c = rng.normal(0, 0.15, (12, 3)) + [0, 0, 0.5]
    centres = np.concatenate([stat_c, blob_c + path[0]]).astype(np.float32)
    # keys at every frame: the spline interpolates the GT path exactly at the frame times
    follow = np.concatenate([np.repeat(stat_c[:, None], len(t), 1), blob_c[:, None] + path[None]], 0)
    good = trajectory_error(_nodes(centres, follow, t), pts, t, dyn)
    frozen = trajectory_error(_nodes(centres, np.repeat(centres[:, None], len(t), 1), t), pts, t, dyn)
    assert good["traj_err_dyn"] < 1e-4 and good["traj_ratio_dyn"] < 1e-3
    assert frozen["traj_ratio_dyn"] == pytest.approx(1.0, abs=1e-5)
    assert frozen["traj_err_dyn"] == pytest.approx(frozen["zero_motion_dyn"], rel=1e-5)
    assert good["zero_motion_dyn"] == pytest.approx(frozen["zero_motion_dyn"]) and good["zero_motion_dyn"] > 0.05
    # half the motion: half the error of zero motion, ratio ~0.5 (the blend is linear in displacement)
    half = np.concatenate([np.repeat(stat_c[:, None], len(t), 1), blob_c[:, None] + (path[0] + 0.5 * (path - path[0]))[None]], 0)
    h = trajectory_error(_nodes(centres, half, t), pts, t, dyn)
    assert 0.4 < h["traj_ratio_dyn"] < 0.6


def test_paired_stats_mean_difference_and_t():
    rows = []
    for scene in ("a", "b"):
        for seed, base in ((0, 20.0), (1, 21.0), (2, 19.0)):
            d = {"a": 1.0, "b": 2.0}[scene] + 0.1 * seed
            rows.append({"scene": scene, "init": "mani", "motion": "spline", "train_seed": seed, "masked_psnr_val": base})
            rows.append({"scene": scene, "init": "fps", "motion": "mlp", "train_seed": seed,
                         "masked_psnr_val": base + d})
    rows.append({"scene": "a", "init": "mani", "motion": "spline", "train_seed": "mean", "masked_psnr_val": 99.0})
    (p,) = paired_stats(rows)
    diffs = np.array([1.0, 1.1, 1.2, 2.0, 2.1, 2.2])
    assert (p["a"], p["b"], p["n"]) == ("mani+spline", "fps+mlp", 6)
    assert p["mean_diff"] == pytest.approx(diffs.mean())
    assert p["t"] == pytest.approx(diffs.mean() / (diffs.std(ddof=1) / np.sqrt(6)))
    assert 0 < p["p"] < 0.01


@pytest.mark.slow
def test_bundle_nodes_on_the_ground_truth_score_near_zero_on_a_generated_scene(tmp_path):
    """~40 s: `engine init` on the tiny generated scene, then the bundle's nodes replaced by
    GT-following / frozen ones; exercises the camera -> GT frame mapping of a real bundle."""
    pytest.importorskip("bpy")
    import dataclasses
    import json
    import subprocess
    import sys
    from pathlib import Path

    import torch

    from engine.bench.node_motion import bundle_train_gt, trained_trajectory_error
    from engine.bundle import load_bundle, write_nodes
    from engine.geometry.hermite import catmull_rom_tangents, hermite_fit

    repo = Path(__file__).resolve().parents[2]
    gen = subprocess.run([sys.executable, "tools/synth_scene.py", "--out", str(tmp_path / "clip"), "--preset", "tiny",
                          "--quiet"], cwd=repo, capture_output=True, text=True, timeout=180)
    assert gen.returncode == 0, gen.stderr[-2000:]
    clip = Path(json.loads(gen.stdout.strip().splitlines()[-1])["out"])
    init = subprocess.run([sys.executable, "-m", "engine", "init", str(clip), "--out", str(tmp_path / "b"),
                           "--cache", str(tmp_path / "cache")], cwd=repo, capture_output=True, text=True, timeout=300)
    assert init.returncode == 0, init.stdout[-2000:] + init.stderr[-2000:]
    bundle = load_bundle(tmp_path / "b")
    points, times, dynamic = bundle_train_gt(bundle, clip)
    assert points.shape[1] == len(times) > 4 and dynamic.any()
    nd = bundle.nodes
    # nodes on GT points (every 2nd), keyed at every training time on those points' true
    # paths (the bundle's own 4 keys over 12 frames cannot hold the motion: ratio 0.35)
    path = torch.as_tensor(points[::2], dtype=torch.float32)
    kt = torch.as_tensor(times)
    keys = hermite_fit(kt, torch.as_tensor(times), path)
    tan = catmull_rom_tangents(kt, keys)
    n, k = keys.shape[:2]
    quat = np.zeros((n, k, 4), np.float32)
    quat[..., 0] = 1
    follow = dataclasses.replace(nd, centers=path[:, 0].numpy(), key_times=times, radii=np.full(n, float(np.median(nd.radii)), np.float32),
                                 pos_keys=keys.numpy(), pos_tangents=tan.numpy(), rot_keys=quat,
                                 rot_tangents=np.zeros_like(quat), p_dyn=None, bind_idx=None, bind_w=None,
                                 graph_idx=None, pos_tangents_in=None, rot_tangents_in=None)
    write_nodes(tmp_path / "b" / "nodes.npz", follow)
    good = trained_trajectory_error(tmp_path / "b", clip)
    frozen_keys = path[:, :1].expand(-1, k, -1).contiguous()
    write_nodes(tmp_path / "b" / "nodes.npz", dataclasses.replace(follow, pos_keys=frozen_keys.numpy(),
                                                                  pos_tangents=np.zeros_like(frozen_keys.numpy())))
    frozen = trained_trajectory_error(tmp_path / "b", clip)
    assert frozen["traj_ratio_dyn"] == pytest.approx(1.0, abs=1e-4)
    assert good["zero_motion_dyn"] == pytest.approx(frozen["zero_motion_dyn"])
    assert good["traj_ratio_dyn"] < 0.1, good  # measured 0.05


def test_trajectory_error_counts_the_nodes_turn():
    """A spinning disc: nodes that follow its centre *and* turn with it carry every point of it;
    the same nodes without their rotation leave the rim behind (the measure used to ignore
    rotation keys, so a rolling ball's nodes could not score better than translating ones)."""
    from engine.geometry.quaternion import quat_from_axis_angle

    import torch

    F = 12
    t = np.linspace(0, 1, F).astype(np.float32)
    ang = 1.5 * t  # 1.5 rad over the clip
    rng = np.random.default_rng(0)
    local = np.concatenate([rng.uniform(-0.4, 0.4, (200, 2)), np.zeros((200, 1))], 1)
    c, s = np.cos(ang), np.sin(ang)
    rotz = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1),
                     np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], 1)  # [F, 3, 3]
    pts = np.einsum("fij,mj->mfi", rotz, local).astype(np.float32)  # [M, F, 3]
    dyn = np.ones(len(pts), bool)
    centres = np.zeros((1, 3), np.float32)
    nodes = _nodes(centres, np.zeros((1, F, 3)), t)
    nodes.radii[:] = 5.0
    still = trajectory_error(nodes, pts, t, dyn)
    q = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]).expand(F, 3), torch.as_tensor(ang)).numpy()[None]
    from engine.geometry.hermite import catmull_rom_tangents

    nodes.rot_keys[:] = q
    nodes.rot_tangents[:] = catmull_rom_tangents(torch.as_tensor(t), torch.as_tensor(q)).numpy()
    turned = trajectory_error(nodes, pts, t, dyn)
    assert still["traj_ratio_dyn"] == pytest.approx(1.0, abs=1e-5)
    assert turned["traj_ratio_dyn"] < 0.02, turned


def test_rotation_error_scores_turning_nodes_against_the_objects_turn():
    """Nodes on a spinning disc: with the disc's rotation their error is ~0, without it the
    error is the disc's own turn; nodes off every moving point are not scored."""
    from engine.bench.node_motion import rotation_error
    from engine.geometry.hermite import catmull_rom_tangents
    from engine.geometry.quaternion import quat_from_axis_angle

    import torch

    F = 13
    t = np.linspace(0, 1, F).astype(np.float32)
    ang = 1.2 * t
    rng = np.random.default_rng(0)
    local = np.concatenate([rng.uniform(-0.4, 0.4, (300, 2)), np.zeros((300, 1))], 1)
    c, s = np.cos(ang), np.sin(ang)
    rotz = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1),
                     np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], 1)
    disc = np.einsum("fij,mj->mfi", rotz, local)
    wall = np.repeat(rng.uniform(-3, 3, (300, 1, 3)) + [0, 0, 4], F, 1)  # static points far behind
    pts = np.concatenate([disc, wall]).astype(np.float32)
    dynamic = np.r_[np.ones(300, bool), np.zeros(300, bool)]
    object_id = np.r_[np.ones(300, int), np.zeros(300, int)]
    on_disc = disc[:5]  # five nodes riding on disc points
    far = np.repeat(np.array([[[10.0, 10.0, 10.0]]]), F, 1)  # one node near nothing
    nodes = _nodes(np.concatenate([on_disc[:, F // 2], far[:, 0]]).astype(np.float32),
                   np.concatenate([on_disc, far]), t)
    still = rotation_error(nodes, pts, t, object_id, dynamic)
    q = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]).expand(F, 3), torch.as_tensor(ang)).numpy()
    nodes.rot_keys[:] = q[None]
    nodes.rot_tangents[:] = catmull_rom_tangents(torch.as_tensor(t), torch.as_tensor(q[None]).expand(6, F, 4)).numpy()
    turned = rotation_error(nodes, pts, t, object_id, dynamic)
    assert still["rot_nodes"] == turned["rot_nodes"] == 5
    assert turned["rot_err_dyn_deg"] < 0.05
    assert still["rot_err_dyn_deg"] == pytest.approx(still["rot_gt_dyn_deg"], abs=1e-6)
    assert still["rot_gt_dyn_deg"] == pytest.approx(np.degrees(0.3), abs=0.5)  # median |turn| from mid-clip: 1.2 rad x 1/4
