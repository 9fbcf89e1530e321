"""Trajectory triangulation of lifted tracks and the "as static as possible" depth scale."""

import math

import torch

from engine.geometry.camera import camera_centers, look_at, project
from engine.geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_fit
from engine.nodes import (NodeInitConfig, assemble_nodeset, node_depth_scales, rescale_along_rays,
                          track_depth_scales, triangulate_tracks3d)


def _orbit(frames=40, radius=6.0, arc=1.2):
    """Cameras on an arc around the origin (a smooth path, as in the generated scenes)."""
    ang = torch.linspace(-arc / 2, arc / 2, frames, dtype=torch.float64)
    eyes = torch.stack([radius * torch.sin(ang), -radius * torch.cos(ang), 1.5 + 0.2 * torch.sin(3 * ang)], 1)
    w2c = torch.stack([look_at(e, torch.zeros(3, dtype=torch.float64)) for e in eyes]).float()
    return w2c, camera_centers(w2c.double()).float()


def _moving_points(n=16, frames=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, frames)
    start = torch.rand(n, 1, 3, generator=g) - 0.5
    phase = torch.rand(n, 1, 1, generator=g) * 6
    path = torch.stack([0.6 * torch.sin(2 * math.pi * t), 0.4 * t, 0.3 * torch.cos(2 * math.pi * t)], -1)
    return t, start + path.unsqueeze(0) + 0.05 * torch.sin(phase + 4 * t[None, :, None])


def test_triangulation_removes_per_frame_depth_noise_that_the_plain_fit_keeps():
    w2c, cam = _orbit()
    times, X = _moving_points()
    g = torch.Generator().manual_seed(1)
    noise = torch.exp(0.08 * torch.randn(X.shape[:2], generator=g))  # ±8 % depth, independent per frame
    y = rescale_along_rays(X, cam.unsqueeze(0), noise.unsqueeze(-1))  # the lift with a noisy depth prior
    y[3, :10] = float("nan")  # a partial track
    key_times = torch.linspace(0, 1, 10)
    keys = hermite_fit(key_times, times, y, smoothness=1e-2)
    plain = hermite_eval(key_times, keys, catmull_rom_tangents(key_times, keys), times)
    tri = triangulate_tracks3d(y, cam, times, key_times, along_weight=1e-3, smoothness=1e-3)
    assert torch.isnan(tri[3, :10]).all() and torch.isfinite(tri[3, 10:]).all()  # NaN pattern kept
    ok = torch.isfinite(y).all(-1)
    err_plain = (plain - X).norm(dim=-1)[ok].mean()
    err_tri = (tri - X).norm(dim=-1)[ok].mean()
    assert err_tri < 0.75 * err_plain, (float(err_tri), float(err_plain))
    # (only by ~1.5x: with a smooth camera path a slowly varying depth error is not observable,
    # the rays pin down the fast part of the noise)
    # the triangulated points stay on their camera rays: same pixels as the observations
    K = torch.tensor([[200.0, 0, 64], [0, 200.0, 48], [0, 0, 1]]).expand(len(times), 3, 3)
    uv_y, _ = project(K.unsqueeze(0), w2c.unsqueeze(0), torch.nan_to_num(y))
    uv_t, _ = project(K.unsqueeze(0), w2c.unsqueeze(0), torch.nan_to_num(tri))
    assert (uv_y - uv_t).norm(dim=-1)[ok].mean() < 0.5  # pixels


def test_triangulation_leaves_static_tracks_alone():
    w2c, cam = _orbit(frames=12)
    still = torch.tensor([[0.3, -0.2, 0.4]]).expand(12, 3).unsqueeze(0).clone()
    out = triangulate_tracks3d(still, cam, torch.linspace(0, 1, 12), torch.linspace(0, 1, 4))
    assert torch.equal(out, still)


def test_depth_scale_undoes_a_biased_prior_on_static_points_and_keeps_short_tracks():
    w2c, cam = _orbit(frames=30)
    X = torch.tensor([[0.2, 0.1, 0.3], [-0.4, 0.3, 0.0], [0.0, 0.0, 0.5]]).unsqueeze(1).expand(-1, 30, -1)
    biased = rescale_along_rays(X, cam.unsqueeze(0), torch.tensor([1.3, 0.8, 1.5]).view(3, 1, 1))
    biased[2, 5:] = float("nan")  # 5 samples: too short to judge
    s = track_depth_scales(biased, cam, min_len=8)
    assert torch.allclose(s[:2], torch.tensor([1 / 1.3, 1 / 0.8]), rtol=1e-4)
    assert s[2] == 1.0
    assert torch.allclose(rescale_along_rays(biased[:2], cam.unsqueeze(0), s[:2, None, None]), X[:2], atol=1e-4)


def test_depth_scale_recovers_a_moving_point_whose_motion_is_not_the_cameras():
    w2c, cam = _orbit(frames=40)
    t = torch.linspace(0, 1, 40)
    X = (torch.stack([torch.zeros_like(t), torch.zeros_like(t), 0.4 * torch.sin(2 * math.pi * t)], -1)).unsqueeze(0)  # bobs up/down
    biased = rescale_along_rays(X, cam.unsqueeze(0), torch.tensor(1.4))
    s = track_depth_scales(biased, cam)
    assert abs(float(s[0]) * 1.4 - 1.0) < 0.05
    # lifted with the prior's depth the point would "move" with the camera by 40 % of its path
    fake = (biased[0] - biased[0, :1]).norm(dim=-1).max()
    fixed = rescale_along_rays(biased, cam.unsqueeze(0), s[:, None, None])
    assert (fixed[0] - X[0]).norm(dim=-1).max() < 0.1 * fake


def test_nodes_slide_along_their_source_ray_onto_rescaled_tracks():
    w2c, cam = _orbit(frames=24)
    times = torch.linspace(0, 1, 24)
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(60, 3, generator=g) - 0.5).unsqueeze(1).expand(-1, 24, -1)  # static surface points
    biased = rescale_along_rays(pts, cam.unsqueeze(0), torch.tensor(1.25))  # the prior 25 % too far
    src = torch.tensor([0, 5, 10, 23])
    centers = biased[torch.tensor([0, 1, 2, 3]), src]  # nodes sit on biased tracks
    radii = torch.full((4,), 0.2)
    s = node_depth_scales(centers, src, radii, biased, track_depth_scales(biased, cam))
    assert torch.allclose(s, torch.full((4,), 0.8), atol=1e-3)
    cfg = NodeInitConfig(depth_scale=True, num_keys=4, graph_k=2, radius_k=2)
    ns = assemble_nodeset(centers, times[src], torch.zeros(4), biased, times, cfg, w2c)
    assert torch.allclose(ns.centers, pts[:4, 0], atol=1e-3)  # back on the true surface
    K = torch.tensor([[200.0, 0, 64], [0, 200.0, 48], [0, 0, 1]]).expand(4, 3, 3)
    uv0, _ = project(K, w2c[src], centers)
    uv1, _ = project(K, w2c[src], ns.centers)
    assert torch.allclose(uv0, uv1, atol=1e-3)  # same pixel in the source frame
    assert (ns.pos_keys - ns.centers.unsqueeze(1)).norm(dim=-1).max() < 1e-3  # static surface: static nodes
    off = assemble_nodeset(centers, times[src], torch.zeros(4), biased, times, NodeInitConfig(num_keys=4, graph_k=2, radius_k=2), w2c)
    assert torch.equal(off.centers, centers)  # opt-in
