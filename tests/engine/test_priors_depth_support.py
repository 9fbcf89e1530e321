"""Opt-in occluder/support fill of moving regions in the sparse depth prior (``moving_fill='support'``)."""

import numpy as np
import pytest

from engine.errors import InputError
from engine.priors.depth import estimate_depth, support_fill

F_PX, W, H = 120.0, 240, 180
CX, CY = 120.0, 90.0
CAM_H, WALL_Z = 1.5, 12.0            # floor 1.5 below the camera (y down), wall at z = 12
BOX_Z, BOX_HALF_W, BOX_H = 6.0, 0.6, 1.5   # box front face at z = 6, standing on the floor


def _scene(seed=0):
    """Analytic frame: floor + far wall + a box standing on the floor -> (rgb, depth, box mask)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    x, y = (u - CX) / F_PX, (v - CY) / F_PX  # ray direction per unit depth
    floor = np.where(y > 1e-6, CAM_H / np.maximum(y, 1e-6), np.inf)
    depth = np.minimum(floor, WALL_Z)
    box = (np.abs(x * BOX_Z) <= BOX_HALF_W) & (y * BOX_Z >= CAM_H - BOX_H) & (y * BOX_Z <= CAM_H) & (depth > BOX_Z)
    depth = np.where(box, BOX_Z, depth).astype(np.float32)
    rng = np.random.default_rng(seed)
    # world-space checker texture (0.5-unit cells) on floor and wall: the edge-aware fill needs edges
    on_floor = floor < WALL_Z
    X, Y = x * depth, y * depth
    cell = np.where(on_floor, np.floor(X / 0.5) + np.floor(depth / 0.5), np.floor(X / 0.5) + np.floor(Y / 0.5)) % 2
    base = np.where(on_floor[..., None], [150, 110, 70], [200, 200, 200]).astype(np.float32)
    rgb = base + 50.0 * (cell[..., None] - 0.5)
    rgb = np.where(box[..., None], [40, 60, 200], rgb) + rng.normal(0, 4, (H, W, 3))
    return np.clip(rgb, 0, 255).astype(np.uint8), depth, box


def _anchors(depth, box, n=3000, seed=0):
    rng = np.random.default_rng(seed)
    ys, xs = np.nonzero(~box)
    i = rng.choice(len(ys), n, replace=False)
    return np.stack([xs[i] + 0.5, ys[i] + 0.5, depth[ys[i], xs[i]]], 1).astype(np.float32)


def _cams():
    K = np.array([[F_PX, 0, CX], [0, F_PX, CY], [0, 0, 1]], np.float64)[None]
    return K, np.eye(4)[None]


def test_support_fill_places_box_on_its_floor_contact():
    rgb, gt, box = _scene()
    K, w2c = _cams()
    dyn = box[None].astype(np.float32)
    a = [_anchors(gt, box)]
    old, _ = estimate_depth(rgb[None], K, w2c, anchors=a, dynamic=dyn)
    new, _ = estimate_depth(rgb[None], K, w2c, anchors=a, dynamic=dyn, moving_fill="support")
    r_old = float(np.median(old[0][box] / gt[box]))
    r_new = float(np.median(new[0][box] / gt[box]))
    # the surround fill takes the wall / floor behind the box: far too deep
    assert r_old > 1.3, r_old
    # the support fill takes the floor just below the box (slightly in front of its face)
    assert 0.8 < r_new < 1.1, r_new
    # static pixels are untouched
    assert np.array_equal(old[0][~box], new[0][~box])


def test_support_fill_never_deepens_and_keeps_outside():
    rng = np.random.default_rng(1)
    depth = rng.uniform(2.0, 10.0, (60, 80)).astype(np.float32)
    moving = np.zeros((60, 80), bool)
    moving[20:35, 30:45] = True
    moving[5:9, 5:9] = True  # too small (< min_px): left alone
    out = support_fill(depth, moving, min_px=20)
    assert np.all(out <= depth)
    assert np.array_equal(out[~moving], depth[~moving])
    assert np.array_equal(out[5:9, 5:9], depth[5:9, 5:9])
    big = out[20:35, 30:45]
    assert np.all(big <= np.percentile(depth[~moving], 50))  # capped by a low ring percentile
    # no moving pixels, or a region with no ring around it: unchanged
    assert np.array_equal(support_fill(depth, np.zeros_like(moving)), depth)
    assert np.array_equal(support_fill(depth, np.ones_like(moving)), depth)


def test_support_fill_per_region_values():
    # two regions on a left-near / right-far depth ramp each take their own surroundings
    depth = np.tile(np.linspace(2.0, 10.0, 100, dtype=np.float32), (40, 1))
    moving = np.zeros((40, 100), bool)
    moving[10:30, 10:20] = True
    moving[10:30, 80:90] = True
    out = support_fill(depth, moving, q=0.0)
    left, right = out[10:30, 10:20], out[10:30, 80:90]
    assert np.allclose(left, left.min()) and np.allclose(right, right.min())
    assert left.max() < depth[0, 10] and right.max() < depth[0, 80]
    assert right.min() > left.max() + 4.0


def test_moving_fill_validation_and_default_unchanged():
    rgb, gt, box = _scene()
    K, w2c = _cams()
    a = [_anchors(gt, box)]
    with pytest.raises(InputError):
        estimate_depth(rgb[None], K, w2c, anchors=a, moving_fill="nearest")
    d0, _ = estimate_depth(rgb[None], K, w2c, anchors=a)
    d1, _ = estimate_depth(rgb[None], K, w2c, anchors=a, moving_fill="support")  # no dynamic prior: no-op
    assert np.array_equal(d0, d1)
