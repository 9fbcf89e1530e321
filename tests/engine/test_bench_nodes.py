"""``python -m engine.bench nodes``: rows have the documented keys and finite values, and on
the procedural scene (known motion) MANI's node allocation and spline fit beat the baselines.

The generated-scene test needs bpy (tiny preset, a few seconds to generate + prepare);
the procedural test runs everywhere. No timing asserts.
"""

from __future__ import annotations

import argparse
import math

import pytest

from engine.bench import nodes as bench

GT_KEYS = ("scene", "init", "trajectory", "nodes", "dyn_frac", "dyn_share_gt", "density_ratio", "traj_err",
           "traj_err_dyn", "traj_err_abs", "traj_err_dyn_abs", "zero_motion_dyn", "extent", "wall_s")


def _args(**kw):
    parser = argparse.ArgumentParser()
    parser.add_argument("--json", action="store_true")
    bench.add_arguments(parser)
    args = parser.parse_args([])
    for k, v in kw.items():
        setattr(args, k, v)
    return args


def _check(rows, keys, budget):
    assert [(r["init"], r["trajectory"]) for r in rows] == list(bench.VARIANTS)
    for r in rows:
        for k in keys:
            assert k in r, (k, r)
            if isinstance(r[k], float):
                assert math.isfinite(r[k]), (k, r)
        assert r["nodes"] == budget
        assert 0.0 <= r["dyn_frac"] <= 1.0 and r["density_ratio"] >= 0.0
    # static trajectories and spline trajectories share the MANI centres
    assert rows[0]["dyn_frac"] == rows[1]["dyn_frac"]


@pytest.mark.slow
def test_generated_scene_rows(tmp_path):
    pytest.importorskip("bpy")
    pytest.importorskip("cv2")
    rows = bench.run(_args(preset="tiny", keep=str(tmp_path / "tiny"), budget=60, skip_speed=True))
    _check(rows, GT_KEYS, 60)
    assert 0.0 < rows[0]["dyn_share_gt"] < 1.0 and rows[0]["extent"] > 0


@pytest.mark.slow
def test_procedural_rows():
    rows = bench.run(_args(procedural=True, frames=8, budget=60, skip_speed=True))
    _check(rows, ("scene", "init", "trajectory", "nodes", "dyn_frac", "density_ratio", "traj_err", "wall_s"), 60)
    # the known answer on this scene (three moving boxes on a static floor and wall, GT
    # motion): MANI spends its budget on what moves (measured 0.78 of the nodes, 15x the
    # static density) where the motion-blind baselines spread evenly (FPS 0.12, voxel 0.07,
    # tracklet 0.03; density ratio <= 0.55), and fitted splines follow the moving parts
    # better than nodes at rest (0.042 vs 0.087 of the extent)
    by = {(r["init"], r["trajectory"]): r for r in rows}
    mani = by["mani", "spline"]
    for base in ("fps", "voxel", "tracklet"):
        assert mani["dyn_frac"] > 3 * by[base, "spline"]["dyn_frac"], base
        assert by[base, "spline"]["density_ratio"] < 1.0 < mani["density_ratio"] / 5, base
    assert mani["traj_err_dyn"] < 0.7 * by["mani", "static"]["traj_err_dyn"]


def test_gt_motion_ceiling_nodes_follow_the_surface_at_their_pixel():
    import torch

    from engine.geometry.camera import project
    from engine.geometry.hermite import hermite_eval
    from engine.nodes import NodeSet

    scene = bench.make_scene(frames=8, seed=0)
    traj, K, w2c, times, depth = scene["gt_traj"], scene["K"], scene["w2c"], scene["times"], scene["depth"]
    uv, z = project(K.unsqueeze(0), w2c.unsqueeze(0), traj[:, :1].expand(-1, 8, -1))
    col, row = uv[:, 0, 0].floor().long().clamp(0, 255), uv[:, 0, 1].floor().long().clamp(0, 191)
    visible = torch.nonzero((z[:, 0] - depth[0, row, col]).abs() < 1e-3).squeeze(1)
    pick = visible[torch.randperm(visible.numel(), generator=torch.Generator().manual_seed(0))[:20]]
    cam0 = -w2c[0, :3, :3].T @ w2c[0, :3, 3]
    true = traj[pick, 0]
    centers = cam0 + 1.3 * (true - cam0)  # placed 30 % too far along the frame-0 ray
    n, kt = len(pick), torch.linspace(0, 1, 8)
    rot = torch.zeros(n, 8, 4)
    rot[..., 0] = 1
    ns = NodeSet(centers, torch.full((n,), 0.1), kt, centers[:, None].expand(-1, 8, -1).clone(), torch.zeros(n, 8, 3),
                 rot, torch.zeros_like(rot), torch.ones(n), torch.zeros(n, 1, dtype=torch.long), torch.zeros(n), "test")
    gt = {"times": times, "K": K, "w2c": w2c, "points": traj, "depth": depth}
    kept = bench.gt_motion_nodes(ns, gt)
    moved = bench.gt_motion_nodes(ns, gt, at_gt_depth=True)
    assert torch.equal(kept.centers, centers)
    assert (moved.centers - true).norm(dim=-1).max() < 0.1  # the surface at the pixel (pixel footprint)
    path = hermite_eval(kt, moved.pos_keys, moved.pos_tangents, times)
    disp_true = traj[pick] - traj[pick, :1]
    assert ((path - path[:, :1]) - disp_true).norm(dim=-1).mean() < 0.05
    assert torch.allclose(hermite_eval(kt, kept.pos_keys, kept.pos_tangents, times) - centers[:, None],
                          path - moved.centers[:, None], atol=1e-4)  # same motion, other position
