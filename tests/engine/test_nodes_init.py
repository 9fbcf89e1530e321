"""Candidates, track lifting, spline trajectory fit, graph/radii, NodeSet, end-to-end init."""

import numpy as np
import pytest
import torch

from engine.geometry.camera import look_at, project
from engine.geometry.hermite import hermite_eval
from engine.nodes import (NodeInitConfig, NodeSet, ManiConfig, build_candidates, fit_node_trajectories,
                          initialise_nodes, lift_tracks, node_graph, node_radii)


def _camera(frames=3):
    K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]).expand(frames, 3, 3).clone()
    w2c = torch.stack([look_at(torch.tensor([0.2 * f, 0.0, -5.0], dtype=torch.float64),
                               torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)) for f in range(frames)]).float()
    return K, w2c


def test_candidates_backproject_to_points_that_reproject_to_patch_centres():
    K, w2c = _camera()
    depth = torch.full((3, 48, 64), 4.0)
    depth[1, :10] = 0.0  # invalid rows are dropped
    yy, xx = torch.meshgrid(torch.arange(6), torch.arange(8), indexing="ij")
    centers = torch.stack([xx * 8 + 4.0, yy * 8 + 4.0], -1)
    tokens = torch.randn(3, 6, 8, 5)
    fg = torch.zeros(3, 48, 64)
    fg[:, 24:] = 1.0
    c = build_candidates(depth, K, w2c, torch.tensor([0.0, 0.5, 1.0]), tokens, centers, fg, torch.tensor([0, 1]))
    assert c.positions.shape[0] == 48 + 48 - 8  # the first patch row (y = 4) of frame 1
    uv, z = project(K[c.frame], w2c[c.frame], c.positions)
    assert torch.allclose(uv, c.pixel, atol=1e-3) and torch.allclose(z, torch.full_like(z, 4.0), atol=1e-4)
    assert torch.equal(c.fg, (c.pixel[:, 1] > 24).float())
    assert torch.allclose(c.tokens[0], tokens[0, 0, 0])


def test_lift_tracks_roundtrip_and_drops_occluded():
    K, w2c = _camera()
    pts = torch.tensor([[0.1, 0.2, 0.0], [-0.3, 0.1, 0.0]]).unsqueeze(1).expand(-1, 3, -1)
    uv, z = project(K.unsqueeze(0), w2c.unsqueeze(0), pts)
    depth = torch.zeros(3, 48, 64)
    col, row = uv[..., 0].floor().long(), uv[..., 1].floor().long()
    depth[torch.arange(3).expand(2, 3), row, col] = z
    # the nearest-pixel depth is exact only at that pixel; fill neighbours so no depth edge
    depth = torch.nn.functional.max_pool2d(depth.unsqueeze(1), 5, 1, 2).squeeze(1)
    vis = torch.ones(2, 3, dtype=torch.bool)
    vis[1, 2] = False
    x = lift_tracks(uv, vis, depth, K, w2c)
    assert torch.isnan(x[1, 2]).all()
    ok = torch.isfinite(x).all(-1)
    # depth is the exact z at the point's pixel, so the lift is exact up to the pixel's
    # position (uv itself is kept, not snapped)
    assert torch.allclose(x[ok], pts[ok], atol=1e-3)


def test_a_track_with_a_depth_of_its_own_is_lifted_with_it():
    """A sample with its own camera depth (a hinge track on a thin link, whose pixels are all
    depth edge in the map) is lifted with that depth; NaN leaves the map to decide."""
    K, w2c = _camera()
    pts = torch.tensor([[0.1, 0.2, 0.0], [-0.3, 0.1, 0.0]]).unsqueeze(1).expand(-1, 3, -1)
    uv, z = project(K.unsqueeze(0), w2c.unsqueeze(0), pts)
    depth = torch.full((3, 48, 64), 9.0)  # the map sees only a wall behind them
    depth[:, :, ::2] = 12.0  # ... and it is all edge
    vis = torch.ones(2, 3, dtype=torch.bool)
    assert torch.isnan(lift_tracks(uv, vis, depth, K, w2c)).all()
    own = torch.stack([z[0], torch.full((3,), float("nan"))])
    x = lift_tracks(uv, vis, depth, K, w2c, tracks_depth=own)
    assert torch.allclose(x[0], pts[0], atol=1e-4)
    assert torch.isnan(x[1]).all()


def test_spline_fit_recovers_translation_and_fallbacks():
    times = torch.linspace(0, 1, 20)
    key_times = torch.linspace(0, 1, 6)
    disp = torch.stack([torch.sin(3 * times), times ** 2, 0.5 * times], 1)  # [F, 3]
    g = torch.Generator().manual_seed(0)
    anchors = torch.rand(40, 3, generator=g) * 0.2  # tracks around the origin
    tracks = anchors.unsqueeze(1) + disp.unsqueeze(0)
    tracks[28, 10:] += 2.0  # a near-neighbour track that jumps to another surface (IRLS must down-weight it)
    tracks[1:5, 7:9] = float("nan")  # missing samples
    centers = torch.tensor([[0.1, 0.1, 0.1], [0.12, 0.1, 0.1], [50.0, 50.0, 50.0], [50.1, 50.0, 50.0]])
    radii = torch.tensor([0.1, 0.1, 0.1, 0.1])
    graph_idx = torch.tensor([[1], [0], [3], [2]])
    src = torch.zeros(4, dtype=torch.long)
    keys, tans, support = fit_node_trajectories(centers, src, radii, tracks, times, key_times, graph_idx,
                                                k_tracks=8, smoothness=1e-4)
    pred = hermite_eval(key_times, keys, tans, times)
    err = (pred[:2] - (centers[:2].unsqueeze(1) + disp)).norm(dim=-1).max()
    assert err < 0.05, err
    # without IRLS (one plain least-squares pass) the jumping track drags the fit away
    k1, t1, _ = fit_node_trajectories(centers, src, radii, tracks, times, key_times, graph_idx,
                                      k_tracks=8, smoothness=1e-4, irls_iters=1)
    err1 = (hermite_eval(key_times, k1, t1, times)[:2] - (centers[:2].unsqueeze(1) + disp)).norm(dim=-1).max()
    assert err1 > 5 * err
    assert support[2] == 0 and support[3] == 0
    # no supporting tracks anywhere near (and neighbours unsupported too): static
    assert torch.allclose(pred[2], centers[2].expand(20, 3), atol=1e-5)
    # graph fallback: node 3 takes the displacement of a supported neighbour
    graph_idx2 = torch.tensor([[1], [0], [3], [0]])
    keys2, tans2, _ = fit_node_trajectories(centers, src, radii, tracks, times, key_times, graph_idx2, smoothness=1e-4)
    pred2 = hermite_eval(key_times, keys2, tans2, times)
    assert torch.allclose(pred2[3] - centers[3], pred2[0] - centers[0], atol=1e-5)
    keys3, tans3, _ = fit_node_trajectories(centers, src, radii, tracks, times, key_times, graph_idx2,
                                            smoothness=1e-4, fallback="static")
    assert torch.allclose(keys3[3], centers[3].expand(6, 3))


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


@pytest.mark.parametrize("device", DEVICES)
def test_graph_and_radii(device):
    """Also on CUDA: the trainer builds the graph of its (device) nodes; a CPU ``arange``
    here stopped every CUDA training run in ``build_model``."""
    g = torch.Generator().manual_seed(0)
    c = torch.cat([torch.rand(50, 3, generator=g) * 0.1, torch.rand(50, 3, generator=g) * 10 + 20]).to(device)
    idx, d2 = node_graph(c, 6)
    assert idx.device == c.device and d2.device == c.device
    assert idx.shape == (100, 6) and not (idx.cpu() == torch.arange(100).unsqueeze(1)).any()
    r = node_radii(c, 4)
    assert r.device == c.device
    assert r[:50].max() < r[50:].min()  # dense cluster -> small radii
    lone_idx, _ = node_graph(c[:1], 6)  # one node: no neighbours, same device
    assert lone_idx.shape == (1, 0) and lone_idx.device == c.device and node_radii(c[:1]).device == c.device


def test_nodeset_npz_roundtrip():
    n, k = 5, 4
    ns = NodeSet(torch.rand(n, 3), torch.rand(n), torch.linspace(0, 1, k), torch.rand(n, k, 3), torch.rand(n, k, 3),
                 torch.rand(n, k, 4), torch.rand(n, k, 4), torch.rand(n), torch.randint(n, (n, 2)))
    d = ns.to_npz_dict()
    assert d["graph_idx"].dtype == np.int64 and d["centers"].dtype == np.float32
    back = NodeSet.from_npz_dict(d)
    for key in d:
        assert np.array_equal(back.to_npz_dict()[key], d[key])


@pytest.mark.slow
def test_initialise_nodes_end_to_end_on_bench_scene():
    from engine.bench.nodes import evaluate, make_scene

    scene = make_scene(frames=8, h=96, w=128, patch=8, dim=16)
    inputs = {k: scene[k] for k in ("depth", "K", "w2c", "times", "tokens", "patch_centers", "fg",
                                    "tracks_xy", "tracks_vis")}
    budget = 150
    results = {}
    for method, traj in (("mani", "spline"), ("mani", "static"), ("fps", "spline")):
        ns = initialise_nodes(**inputs, config=NodeInitConfig(method=method, trajectory=traj, num_keys=4,
                                                              num_keyframes=4, mani=ManiConfig(budget=budget)))
        assert ns.num_nodes == budget
        assert ns.pos_keys.shape == (budget, 4, 3) and ns.graph_idx.shape == (budget, 8)
        assert torch.isfinite(ns.pos_keys).all() and (ns.radii > 0).all()
        if traj == "static":  # no tracks fitted: the paper's identity start
            assert torch.equal(ns.rot_keys[..., 0], torch.ones(budget, 4))
        else:  # the bench scene's boxes turn: rotations fitted from the tracks (test_node_rotations.py)
            assert torch.allclose(ns.rot_keys.norm(dim=-1), torch.ones(budget, 4), atol=1e-5)
            assert (ns.rot_keys[..., 0] < 0.99).any()
        results[(method, traj)] = evaluate(ns, scene)
    assert results[("mani", "spline")]["density_ratio"] > 2 * results[("fps", "spline")]["density_ratio"]
    assert results[("mani", "spline")]["traj_err"] < 0.7 * results[("mani", "static")]["traj_err"]


def _moving_track_scene(n_tracks=30, frames=24, seed=0):
    """Tracks on a patch that translates in x at depth ~5 in front of a camera rig."""
    K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]).expand(frames, 3, 3).clone()
    w2c = torch.stack([look_at(torch.tensor([0.02 * f, 0.0, -5.0], dtype=torch.float64),
                               torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)) for f in range(frames)]).float()
    times = torch.linspace(0, 1, frames)
    g = torch.Generator().manual_seed(seed)
    anchors = (torch.rand(n_tracks, 3, generator=g) - 0.5) * 0.2
    disp = torch.stack([0.6 * times, 0.1 * torch.sin(6 * times), torch.zeros_like(times)], 1)
    pts = anchors.unsqueeze(1) + disp.unsqueeze(0)  # [P, F, 3]
    uv, _ = project(K.unsqueeze(0), w2c.unsqueeze(0), pts)
    return K, w2c, times, pts, uv, disp


def test_clean_tracks3d_splits_depth_jumps_freezes_static_and_removes_spikes():
    from engine.nodes import clean_tracks3d

    K, w2c, times, pts, uv, _ = _moving_track_scene(n_tracks=4, frames=20)
    f = pts.shape[1]
    raw = pts.clone()
    cam_c = -torch.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])  # camera centres [F, 3]
    # track 0: slides onto the background at frame 12 (lifted point jumps 60 % further along its ray)
    raw[0, 12:] = cam_c[12:] + 1.6 * (raw[0, 12:] - cam_c[12:])
    # track 1: a single-frame depth flicker of 6 % at frame 7 (below the jump threshold)
    raw[1, 7] = cam_c[7] + 1.06 * (raw[1, 7] - cam_c[7])
    # track 2: only 3 samples -> dropped
    raw[2, 3:] = float("nan")
    fg = torch.ones(f, 48, 64)
    out, src = clean_tracks3d(raw, uv, K, w2c, fg)
    assert src.tolist() == [0, 0, 1, 3]  # track 0 split in two, track 2 dropped
    first, second = out[0], out[1]
    assert torch.isfinite(first[:12]).all() and torch.isnan(first[12:]).all()
    assert torch.isnan(second[:12]).all() and torch.isfinite(second[12:]).all()
    assert torch.allclose(out[2], pts[1], atol=1e-3)  # the spike is gone, the motion is kept
    assert torch.allclose(out[3], pts[3], atol=1e-3)  # a clean moving track passes unchanged
    # a static prior freezes tracks: depth flicker there is noise, not motion
    noisy = pts.clone()
    noisy[:, 1::2] = cam_c[1::2] + 1.05 * (noisy[:, 1::2] - cam_c[1::2])
    frozen, _ = clean_tracks3d(noisy, uv, K, w2c, torch.zeros(f, 48, 64))
    assert (frozen - frozen[:, :1]).abs().max() < 1e-6


def test_spline_fit_keeps_true_motion_with_sliding_tracks_and_falls_back_on_garbage():
    from engine.nodes import clean_tracks3d

    K, w2c, times, pts, uv, disp = _moving_track_scene(n_tracks=30, frames=24)
    cam_c = -torch.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])
    raw = pts.clone()
    # 8 of 30 tracks slide onto a far background at frames 6..20 and stay there
    for i, start in zip(range(0, 30, 4), range(6, 24, 2)):
        bg = cam_c[start] + 1.8 * (pts[i, start] - cam_c[start])
        raw[i, start:] = bg
    fg = torch.ones(24, 48, 64)
    clean, _ = clean_tracks3d(raw, uv, K, w2c, fg)
    key_times = torch.linspace(0, 1, 6)
    centers = torch.tensor([[0.0, 0.0, 0.0], [30.0, 30.0, 30.0]])
    radii = torch.tensor([0.1, 0.1])
    src = torch.zeros(2, dtype=torch.long)
    errs = []
    for tracks in (clean, raw):
        keys, tans, support = fit_node_trajectories(centers, src, radii, tracks, times, key_times, None,
                                                    k_tracks=8, smoothness=1e-4, fallback="static")
        errs.append((hermite_eval(key_times, keys, tans, times)[0] - (centers[0] + disp)).norm(dim=-1).max())
    assert errs[0] < 0.03, errs  # cleaned tracks: the node follows the patch
    assert errs[1] > 2 * errs[0], errs  # the sliding tracks would have dragged it
    # garbage: tracks around node 1 whose displacements are independent random walks
    g = torch.Generator().manual_seed(1)
    junk = centers[1] + 0.02 * torch.randn(12, 1, 3, generator=g) + 0.3 * torch.randn(12, 24, 3, generator=g).cumsum(1) * (
        torch.arange(24) > 0).float()[None, :, None]
    keys, tans, support = fit_node_trajectories(centers, src, radii, junk, times, key_times, None, k_tracks=8,
                                                smoothness=1e-4, fallback="static")
    assert support[1] > 0  # it had tracks ...
    assert torch.allclose(keys[1], centers[1].expand(6, 3))  # ... but their fit explains nothing: static
    keys_off, _, _ = fit_node_trajectories(centers, src, radii, junk, times, key_times, None, k_tracks=8,
                                           smoothness=1e-4, fallback="static", max_residual_ratio=None)
    assert (keys_off[1] - centers[1]).norm(dim=-1).max() > 0.05  # without the test it would move
