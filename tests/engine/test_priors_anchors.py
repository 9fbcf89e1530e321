"""Depth anchors that a moving point can fake: short tracks bounded by the long ones
(engine.priors.depth.anchors_from_tracks), moving pixels bounded by occlusion order
(engine.priors.depth.merge_moving_depth), and the second depth pass of compute_priors."""

from __future__ import annotations

import numpy as np

from engine.priors.depth import ANCHOR_LONG_VIEWS, anchors_from_tracks, merge_moving_depth
from engine.priors.tracks import Tracks


def _cameras(f=10, step=0.2, focal=100.0, size=(64, 64)):
    """A camera sliding along +x, looking down +z. K [F,3,3], w2c [F,4,4]."""
    h, w = size
    K = np.tile(np.array([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1.0]]), (f, 1, 1))
    w2c = np.tile(np.eye(4), (f, 1, 1))
    w2c[:, 0, 3] = -step * np.arange(f)  # camera centre at x = step * i
    return K, w2c


def _project(K, w2c, X):
    cam = np.einsum("fij,pj->pfi", w2c[:, :3, :3], X) + w2c[None, :, :3, 3]
    uv = np.einsum("fij,pfj->pfi", K, cam)
    return (uv[..., :2] / uv[..., 2:]).astype(np.float32)


def test_a_short_track_in_front_of_the_lens_is_no_anchor():
    """Static points at depth 8-12 seen in every frame, plus two-frame tracks: one at depth
    10 (a real surface seen briefly) and one at depth 0.05 -- what a moving point whose
    motion reads as parallax triangulates to. The near one anchors nothing; the others do."""
    rng = np.random.default_rng(0)
    K, w2c = _cameras()
    f = len(K)
    static = np.column_stack([rng.uniform(-2, 4, 60), rng.uniform(-2, 2, 60), rng.uniform(8, 12, 60)])
    short = np.array([[1.0, 0.0, 10.0], [0.005, 0.0, 0.05]])
    X = np.vstack([static, short])
    xy = _project(K, w2c, X)
    vis = np.ones((len(X), f), bool)
    vis[-2:] = False
    vis[-2:, 4:6] = True  # seen in two frames only
    tr = Tracks(xy, vis, vis.astype(np.float32), np.zeros(len(X), np.int64))
    anchors = anchors_from_tracks(tr, K, w2c, shape=(64, 64))
    a4 = anchors[4]
    assert ANCHOR_LONG_VIEWS > 2
    assert a4[:, 2].min() > 5.0, "the point just in front of the lens must not anchor"
    assert np.isclose(a4[:, 2], 10.0, atol=1e-3).any(), "the briefly seen real surface keeps its anchor"
    assert len(a4) == 61
    # without long tracks there is nothing to bound by: every triangulated track anchors
    only_short = Tracks(xy[-2:], vis[-2:], vis[-2:].astype(np.float32), np.zeros(2, np.int64))
    assert len(anchors_from_tracks(only_short, K, w2c)[4]) == 2


def test_moving_pixels_keep_the_first_pass_within_occlusion_order():
    static = np.full((1, 4, 6), 10.0, np.float32)
    # fine, too near, behind the wall, at the wall (no depth of its own: a fixed camera),
    # just in front of the wall, near
    first = np.array([[[6.0, 0.1, 14.0, 10.0, 9.5, 3.0]] * 4], np.float32)
    moving = np.zeros((1, 4, 6), np.float32)
    moving[:, :, :5] = 1.0  # the last column is static: it takes the static pass whatever the first said
    out = merge_moving_depth(first, static, moving, max_ratio=4.0, front=0.9)
    assert np.allclose(out[0, :, 0], 6.0)  # a plausible moving depth is kept
    assert np.allclose(out[0, :, 1], 2.5)  # no nearer than 1/4 of the surface behind
    assert np.allclose(out[0, :, 2], 9.0)  # in front of the surface it occludes
    assert np.allclose(out[0, :, 3], 9.0)  # a tie with the background is broken in front of it
    assert np.allclose(out[0, :, 4], 9.5)  # a measured depth in front of it is kept
    assert np.allclose(out[0, :, 5], 10.0)
    assert out.dtype == np.float32


def test_compute_priors_drops_anchors_on_moving_pixels(tmp_path, monkeypatch):
    """The depth handed on comes from a second pass with the motion mask's anchors removed;
    the mask is computed on the first pass; both passes and the mask are cached."""
    from engine.priors import cache as C

    calls = []
    f, h, w = 3, 16, 16

    def fake_depth(frames, K, w2c, backend, model, tracks=None, dynamic=None, **kw):
        calls.append(None if dynamic is None else dynamic.copy())
        d = np.full((f, h, w), 5.0 if dynamic is None else 9.0, np.float32)
        return d, np.ones_like(d)

    def fake_mask(frames, K, w2c, depth, *a, **kw):
        assert np.allclose(depth, 5.0), "the motion mask is computed on the first pass"
        m = np.zeros((f, h, w), np.float32)
        m[:, :4, :4] = 1.0
        return m

    monkeypatch.setattr(C._depth, "estimate_depth", fake_depth)
    monkeypatch.setattr(C._motion, "dynamic_mask", fake_mask)
    monkeypatch.setattr(C._tracks, "track_points", lambda *a, **k: Tracks(
        np.zeros((1, f, 2), np.float32), np.ones((1, f), bool), np.ones((1, f), np.float32), np.zeros(1, np.int64)))
    monkeypatch.setattr(C._tokens, "extract_tokens", lambda *a, **k: C._tokens.TokenGrid(
        np.zeros((f, 1, 1, 4), np.float32), np.zeros((1, 1, 2), np.float32), (16, 16)))
    frames = np.zeros((f, h, w, 3), np.uint8)
    K = np.tile(np.eye(3), (f, 1, 1)); w2c = np.tile(np.eye(4), (f, 1, 1))
    cfg = C.PriorConfig(flow_fine=False)
    pr = C.compute_priors(frames, K, w2c, cfg, cache_dir=tmp_path)
    assert calls[0] is None and calls[1] is not None and calls[1][:, :4, :4].min() == 1.0
    # static pixels: the second pass; moving ones: the first pass inside [static / ratio, static]
    assert np.allclose(pr.depth[:, 8:, 8:], 9.0) and np.allclose(pr.depth[:, :4, :4], 5.0)
    assert {"depth_pass1", "dynamic", "depth"} <= set(pr.recomputed)
    again = C.compute_priors(frames, K, w2c, cfg, cache_dir=tmp_path)
    assert len(calls) == 2 and again.recomputed == [] and np.array_equal(again.depth, pr.depth)
