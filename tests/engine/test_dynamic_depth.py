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
