"""A depth model is checked against the triangulated static points before its depth is used
(engine.priors.depth_check), and compute_priors sets aside one that explains them no better
than a flat depth."""

from __future__ import annotations

import numpy as np
import pytest

from engine.priors import cache as C
from engine.priors.depth_check import describe, model_agreement, model_is_usable
from engine.priors.tracks import Tracks

F, H, W, FOCAL = 8, 48, 64, 60.0


def _scene(seed=0, points=400):
    """A camera sliding along +x over a tilted wall ``Z = 6 + 0.4 X`` (depth varies across the
    image and over time). Returns K, w2c, the true depth [F, H, W] and exact tracks of points on
    the wall seen in every frame."""
    K = np.tile(np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]]), (F, 1, 1))
    w2c = np.tile(np.eye(4), (F, 1, 1))
    cx = 0.15 * np.arange(F)
    w2c[:, 0, 3] = -cx
    xn = (np.arange(W) + 0.5 - W / 2) / FOCAL
    z = (6.0 + 0.4 * cx[:, None]) / (1.0 - 0.4 * xn[None, :])  # ray X = cx + Z xn meets the wall
    depth = np.broadcast_to(z[:, None, :], (F, H, W)).astype(np.float32)
    rng = np.random.default_rng(seed)
    u0, v0 = rng.uniform(4, W - 12, points), rng.uniform(4, H - 4, points)  # pixels of frame 0
    zn = (6.0) / (1.0 - 0.4 * (u0 - W / 2) / FOCAL)
    X = np.column_stack([zn * (u0 - W / 2) / FOCAL, zn * (v0 - H / 2) / FOCAL, zn])
    cam = X[:, None, :] + w2c[None, :, :3, 3]
    xy = (cam[..., :2] / cam[..., 2:] * FOCAL + np.array([W / 2, H / 2])).astype(np.float32)
    vis = (xy[..., 0] >= 0) & (xy[..., 0] < W)
    tracks = Tracks(xy, vis, vis.astype(np.float32), np.zeros(points, np.int64))
    return K, w2c, depth, tracks


def _anchors(depth, tracks):
    out = []
    for f in range(F):
        sel = tracks.visible[:, f]
        uv = tracks.xy[sel, f]
        out.append(np.column_stack([uv, depth[f, uv[:, 1].astype(int), uv[:, 0].astype(int)]]).astype(np.float32))
    return out


def test_a_model_that_reads_the_scene_is_used_one_that_does_not_is_not():
    _, _, depth, tracks = _scene()
    anchors = _anchors(depth, tracks)
    rng = np.random.default_rng(1)
    # relative depth up to scale and shift, and the inverse depth of a MiDaS-style model
    good = model_agreement(3.0 * depth + 1.0, "depth", anchors)
    good_inv = model_agreement(2.0 / depth, "inverse", anchors)
    for g in (good, good_inv):
        assert g["frames"] == F and g["ratio"] < 0.05 and g["inverted"] == 0.0 and model_is_usable(g)
    noise = model_agreement(rng.uniform(1, 2, depth.shape).astype(np.float32), "depth", anchors)
    assert noise["ratio"] > 0.9 and not model_is_usable(noise)
    # an inverse depth read as depth (the wrong --depth-output): the fitted scale turns negative,
    # which the line says
    flipped = model_agreement(1.0 / depth, "depth", anchors)
    assert flipped["inverted"] == 1.0 and "--depth-output" in describe(flipped)
    assert "--depth-output" not in describe(good)
    # too few static points to check (a camera that does not translate triangulates none): kept
    none = model_agreement(rng.uniform(1, 2, depth.shape), "depth", [np.zeros((5, 3), np.float32)] * F)
    assert none["frames"] == 0 and none["ratio"] is None and model_is_usable(none)


def _priors(monkeypatch, tmp_path, pred, **cfg):
    K, w2c, depth, tracks = _scene()
    runs = []

    def fake_predictions(frames, model_path, *a, **k):
        runs.append(model_path)
        return pred(depth), "depth"

    monkeypatch.setattr(C._depth, "model_predictions", fake_predictions)
    monkeypatch.setattr(C._tracks, "track_points", lambda *a, **k: tracks)
    monkeypatch.setattr(C._motion, "dynamic_mask", lambda frames, *a, **k: np.zeros(frames.shape[:3], np.float32))
    monkeypatch.setattr(C._tokens, "extract_tokens", lambda *a, **k: C._tokens.TokenGrid(
        np.zeros((F, 1, 1, 4), np.float32), np.zeros((1, 1, 2), np.float32), (16, 16)))
    model = tmp_path / "depth.onnx"
    model.write_bytes(b"not read: the predictions are faked")
    frames = np.zeros((F, H, W, 3), np.uint8)
    frames[..., 0] = (np.arange(W) * 4 % 256).astype(np.uint8)
    config = C.PriorConfig(flow_fine=False, depth_backend="onnx", depth_model=str(model), **cfg)
    pr = C.compute_priors(frames, K, w2c, config, cache_dir=tmp_path / "cache")
    return pr, depth, runs, (frames, K, w2c, config)


def test_compute_priors_keeps_a_model_that_agrees(monkeypatch, tmp_path):
    pr, depth, runs, _ = _priors(monkeypatch, tmp_path, lambda d: 0.5 * d + 2.0)
    assert pr.depth_check["used"] and pr.depth_check["ratio"] < 0.05
    assert np.median(np.abs(pr.depth - depth) / depth) < 0.01  # the model's depth, aligned
    assert len(runs) == 1  # run once for the check and both depth passes


def test_compute_priors_sets_aside_a_model_no_better_than_flat(monkeypatch, tmp_path):
    noise = np.random.default_rng(2).uniform(1, 2, (F, H, W)).astype(np.float32)
    pr, depth, runs, (frames, K, w2c, config) = _priors(monkeypatch, tmp_path, lambda d: noise)
    assert not pr.depth_check["used"] and pr.depth_check["ratio"] > 0.9 and "depth_check" in pr.recomputed
    # the depth handed on is the weight-free one, shared with a run that named no model
    free = C.compute_priors(frames, K, w2c, C.PriorConfig(flow_fine=False), cache_dir=tmp_path / "cache")
    assert np.array_equal(pr.depth, free.depth) and free.depth_check is None
    assert "depth" not in free.recomputed and "depth_pass1" not in free.recomputed
    # the verdict is cached with the priors; 'off' uses the model whatever it scores
    again = C.compute_priors(frames, K, w2c, config, cache_dir=tmp_path / "cache")
    assert again.recomputed == [] and again.depth_check == pr.depth_check and len(runs) == 1
    forced = C.compute_priors(frames, K, w2c, C.PriorConfig(**{**config.__dict__, "depth_check": "off"}),
                              cache_dir=tmp_path / "cache")
    assert forced.depth_check is None and not np.array_equal(forced.depth, pr.depth)


def test_the_bundle_names_the_model_set_aside(tmp_path):
    from engine.pipeline import _prior_sources
    from engine.priors.depth_check import without_depth_model

    model = tmp_path / "mydepth.onnx"
    model.write_bytes(b"x")
    given = C.PriorConfig(depth_backend="onnx", depth_model=str(model))
    check = {"frames": 60, "ratio": 1.14, "error": 0.31, "flat_error": 0.27, "inverted": 0.35, "used": False}
    src = _prior_sources(without_depth_model(given), {"moving_objects": "contact"}, check, given)
    assert src["depth"]["backend"] == "sparse" and src["depth"]["moving_objects"] == "contact"
    assert src["depth"]["check"]["ratio"] == 1.14 and "used" not in src["depth"]["check"]
    assert src["depth"]["set_aside"]["model"] == "mydepth" and src["depth"]["set_aside"]["backend"] == "onnx"
    kept = _prior_sources(given, None, {**check, "ratio": 0.3, "used": True}, given)
    assert kept["depth"]["backend"] == "onnx" and "set_aside" not in kept["depth"]


def test_unknown_depth_check_is_refused(monkeypatch, tmp_path):
    with pytest.raises(ValueError, match="depth_check"):
        _priors(monkeypatch, tmp_path, lambda d: d, depth_check="sometimes")
