"""Depth of moving objects under the weight-free depth prior (engine/priors/dynamic_depth.py)
and the motion mask's colour residual (engine/priors/motion.py) on scenes with known answers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from engine.priors.dynamic_depth import ground_contact_depth, track_consistent_depth  # noqa: E402

F, H, W = 4, 60, 80
HORIZON = 20  # rows above: a wall at depth 10; below: a floor nearing the camera row by row


def _room():
    """Depth [F,H,W] of a wall (10) and a floor (10 at the horizon down to ~3 at the bottom)."""
    rows = np.arange(H, dtype=np.float32)
    floor = 10.0 / (1.0 + 0.06 * np.maximum(rows - HORIZON, 0))
    return np.broadcast_to(floor[:, None], (F, H, W)).copy()


def _blob(top, bottom, left, right):
    dyn = np.zeros((F, H, W), np.float32)
    dyn[:, top:bottom + 1, left:right + 1] = 1.0
    return dyn


def test_contact_depth_is_the_floor_just_below_the_blob():
    depth = _room()
    dyn = _blob(10, 40, 30, 40)  # an upright object standing on the floor at row 40
    prior = depth.copy()
    prior[dyn > 0] = 10.0  # the prior sees the wall / far floor behind it
    contact, stats = ground_contact_depth(prior, dyn, margin_px=4)
    assert stats == {"blobs": F, "with_contact": F}
    inside = contact[dyn > 0]
    want = depth[0, 45, 35]  # first static row below the 4-px margin
    np.testing.assert_allclose(inside, want, rtol=1e-5)
    assert np.isnan(contact[dyn == 0]).all()
    assert want < 0.7 * 10.0  # the test means something: the contact is much nearer than the wall


def test_contact_depth_is_unknown_for_blobs_at_the_bottom_edge_and_specks():
    depth = _room()
    dyn = _blob(30, H - 1, 10, 20)
    dyn[:, 5:7, 60:62] = 1.0  # 4 px: a speck of noise in the prior
    contact, stats = ground_contact_depth(depth, dyn)
    assert stats["with_contact"] == 0 and stats["blobs"] == 2 * F
    assert np.isnan(contact).all()


def _track(xy_per_frame):
    xy = np.asarray(xy_per_frame, np.float32)[None]
    return xy, np.ones(xy.shape[:2], bool)


def test_track_depth_takes_the_contact_when_nearer_than_the_prior():
    depth = _room()
    dyn = _blob(10, 40, 30, 40)
    prior = depth.copy()
    prior[dyn > 0] = 10.0
    xy, vis = _track([[35.5, 20.5]] * F)
    contact, _ = ground_contact_depth(prior, dyn, margin_px=4)
    with_contact, st = track_consistent_depth(prior, dyn, xy, vis, contact=contact)
    without, _ = track_consistent_depth(prior, dyn, xy, vis)
    assert st["moving_tracks"] == 1
    np.testing.assert_allclose(with_contact[dyn > 0], depth[0, 45, 35], rtol=1e-5)
    np.testing.assert_allclose(without[dyn > 0], 10.0, rtol=1e-5)
    np.testing.assert_array_equal(with_contact[dyn == 0], prior[dyn == 0])  # static pixels untouched


def test_track_depth_is_in_front_of_what_it_was_seen_against():
    """A track seen against a far wall (10) in three frames and a nearer surface (4) in one:
    the occlusion-order percentile (10) keeps it in front of both; the median says ~10."""
    depth = np.full((F, H, W), 10.0, np.float32)
    depth[3] = 4.0
    dyn = np.ones((F, H, W), np.float32)
    xy, vis = _track([[20.5, 20.5]] * F)
    low, _ = track_consistent_depth(depth, dyn, xy, vis, percentile=10.0)
    med, _ = track_consistent_depth(depth, dyn, xy, vis, percentile=50.0)
    assert low[0, 20, 20] < 6.0 and med[0, 20, 20] > 9.0


def _orbit(frames=9, radius=5.0, sweep=1.2):
    """``(K [F,3,3], w2c [F,4,4])``: a camera orbiting the origin at ``radius`` through ``sweep``
    radians, looking at it (the generated scenes' camera path, without its wobble)."""
    import torch

    from engine.geometry.camera import intrinsics, look_at

    az = np.linspace(-sweep / 2, sweep / 2, frames)
    w2c = np.stack([look_at(torch.tensor([radius * np.sin(a), -radius * np.cos(a), 1.0]),
                            torch.zeros(3, dtype=torch.float64)).numpy() for a in az])
    K = np.broadcast_to(intrinsics(80.0, 80.0, W / 2, H / 2).numpy(), (frames, 3, 3)).copy()
    return K, w2c


def test_track_depth_follows_the_camera_for_a_point_at_rest():
    """A point 1.5 units off the orbit's centre, labelled moving (e.g. the slow base of an arm),
    seen by a camera orbiting 70 degrees: its true camera depth changes by ~1.4x over the clip.
    The prior reads its true depth in every frame. With the cameras each frame's painted depth
    is the point's own; one depth for the whole track is off by >10 % at the ends."""
    import torch

    from engine.geometry.camera import project

    K, w2c = _orbit()
    f = len(w2c)
    point = torch.tensor([1.5, -1.0, 0.3], dtype=torch.float64)
    uv, z = project(torch.as_tensor(K), torch.as_tensor(w2c), point.expand(f, 3))
    uv, z = uv.numpy(), z.numpy()
    assert z.max() / z.min() > 1.3  # the test means something: the camera's motion changes the depth
    depth = np.broadcast_to(z[:, None, None], (f, H, W)).astype(np.float32).copy()
    dyn = np.ones((f, H, W), np.float32)
    xy, vis = uv[None].astype(np.float32), np.ones((1, f), bool)
    rows, cols = np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)
    assert ((rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)).all()
    moved, _ = track_consistent_depth(depth, dyn, xy, vis, K=K, w2c=w2c)
    fixed, _ = track_consistent_depth(depth, dyn, xy, vis)
    at_track = moved[np.arange(f), rows, cols]
    np.testing.assert_allclose(at_track, z, rtol=0.02)
    assert np.abs(fixed[np.arange(f), rows, cols] / z - 1).max() > 0.1


def test_track_depth_with_a_camera_at_rest_is_one_depth():
    """A camera that does not move changes no depth: with or without the cameras, the same."""
    K, w2c = _orbit(frames=F, sweep=0.0)
    depth = np.full((F, H, W), 10.0, np.float32)
    depth[3] = 4.0
    dyn = np.ones((F, H, W), np.float32)
    xy, vis = _track([[20.5, 20.5]] * F)
    with_cams, _ = track_consistent_depth(depth, dyn, xy, vis, K=K, w2c=w2c)
    without, _ = track_consistent_depth(depth, dyn, xy, vis)
    np.testing.assert_allclose(with_cams, without, rtol=1e-5)


def _bar_clip(speed=7, width=3, frames=9):
    """Static camera over a textured plane (depth 5); a thin vertical bar of a different texture
    sweeps right at ``speed`` px per frame: too thin and fast for forward-backward-consistent flow."""
    rng = np.random.default_rng(0)
    h, w = 96, 128
    bg = (rng.random((h // 4, w // 4, 3)) * 255).astype(np.uint8).repeat(4, 0).repeat(4, 1)
    bar = (rng.random((h, width, 3)) * 255).astype(np.uint8)
    frames_, mask = [], []
    for f in range(frames):
        img = bg.copy()
        m = np.zeros((h, w), bool)
        x0 = 20 + speed * f
        img[16:80, x0:x0 + width] = bar[16:80]
        m[16:80, x0:x0 + width] = True
        frames_.append(img)
        mask.append(m)
    K = np.tile(np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]]), (frames, 1, 1))
    w2c = np.tile(np.eye(4), (frames, 1, 1))
    return np.stack(frames_), np.stack(mask), K, w2c, np.full((frames, h, w), 5.0, np.float32)


def test_colour_residual_finds_a_thin_fast_bar_the_flow_loses():
    from engine.priors.motion import motion_mask

    frames, mask, K, w2c, depth = _bar_clip()
    inner = slice(2, -2)  # frames with both neighbours at every gap
    recall = {}
    for photometric in (False, True):
        pred = motion_mask(frames, K, w2c, depth, photometric=photometric)[inner] >= 0.5
        recall[photometric] = (pred & mask[inner]).sum() / mask[inner].sum()
        false_pos = (pred & ~mask[inner]).sum() / (~mask[inner]).sum()
        assert false_pos < 0.1, (photometric, false_pos)
    assert recall[True] >= 0.6 and recall[True] >= recall[False] + 0.2, recall
