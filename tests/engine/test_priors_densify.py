"""The weight-free depth's densification (engine.priors.depth.densify) keeps what its anchors say."""

from __future__ import annotations

import numpy as np

from engine.priors.depth import densify


def _receding_plane(h=180, w=240, cell=8, seed=0):
    """A textured floor receding from 2 to 8 units (inverse depth linear in the row, as for a
    plane seen by a pinhole camera) under a checker of random colours: edges every ``cell`` px."""
    rng = np.random.default_rng(seed)
    colours = rng.integers(40, 220, size=(h // cell + 1, w // cell + 1, 3), dtype=np.uint8)
    ys, xs = np.mgrid[0:h, 0:w]
    frame = colours[ys // cell, xs // cell]
    inv = 1 / 8.0 + (1 / 2.0 - 1 / 8.0) * ys / (h - 1)
    return np.ascontiguousarray(frame), (1.0 / inv).astype(np.float32)


def _anchors(depth, n, rng):
    h, w = depth.shape
    u = rng.uniform(0, w, n); v = rng.uniform(0, h, n)
    return np.stack([u, v, depth[v.astype(int), u.astype(int)]], 1).astype(np.float32)


def test_densify_does_not_shrink_toward_the_median():
    """Anchors on one plane in ~1 of 4 checker squares: the dense depth honours them (the old
    median floor moved the far rows ~2 % nearer and the near rows farther)."""
    frame, depth = _receding_plane()
    anchors = _anchors(depth, 700, np.random.default_rng(1))
    d, conf = densify(frame, anchors)
    rel = (d - depth) / depth
    u, v = anchors[:, 0].astype(int), anchors[:, 1].astype(int)
    assert np.median(np.abs(rel[v, u])) < 0.008
    assert np.median(np.abs(rel)) < 0.02
    far, near = rel[:30], rel[-30:]
    assert abs(np.median(far)) < 0.01 and abs(np.median(near)) < 0.01
    assert conf.min() >= 0 and conf.max() <= 1


def test_densify_fills_an_unanchored_region_from_its_neighbours():
    """A region walled off by edges with no anchor inside takes the depth around it, not the
    frame's median depth."""
    frame, depth = _receding_plane()
    frame[150:175, 100:140] = (255, 0, 0)  # a patch with its own colour near the bottom (near rows)
    rng = np.random.default_rng(2)
    anchors = _anchors(depth, 3000, rng)
    inside = (anchors[:, 1] >= 145) & (anchors[:, 1] < 180) & (anchors[:, 0] >= 95) & (anchors[:, 0] < 145)
    anchors = anchors[~inside]
    d, _ = densify(frame, anchors)
    patch = (d[155:170, 110:130] - depth[155:170, 110:130]) / depth[155:170, 110:130]
    median_depth = float(np.median(anchors[:, 2]))
    assert np.median(np.abs(patch)) < 0.05, np.median(patch)
    assert abs(np.median(d[155:170, 110:130]) - median_depth) > 0.5  # not the median (~3.4 units)
