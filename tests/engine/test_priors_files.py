"""Precomputed prior files (validation names the file) and the prior cache (invalidation by dependency)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import test_priors_scene as scene  # noqa: E402

from engine.errors import InputError  # noqa: E402
from engine.priors import PriorConfig, compute_priors, load_depth, load_mask, load_tracks  # noqa: E402
from engine.priors import cache as cache_mod  # noqa: E402

SHAPE = (3, 10, 12)


def test_depth_npy_and_png(tmp_path):
    d = np.random.default_rng(0).uniform(1, 5, SHAPE).astype(np.float32)
    np.save(tmp_path / "d.npy", d)
    assert np.array_equal(load_depth(tmp_path / "d.npy", SHAPE), d)
    with pytest.raises(InputError) as e:
        load_depth(tmp_path / "d.npy", (4, 10, 12))
    assert "d.npy" in str(e.value)
    folder = tmp_path / "dpng"; folder.mkdir()
    for f in range(3):
        cv2.imwrite(str(folder / f"{f:04d}.png"), np.round(d[f] / 0.001).astype(np.uint16))
    with pytest.raises(InputError) as e:
        load_depth(folder, SHAPE)
    assert "scale.json" in str(e.value)
    (folder / "scale.json").write_text(json.dumps({"scale": 0.001}))
    assert np.allclose(load_depth(folder, SHAPE), d, atol=1e-3)
    cv2.imwrite(str(folder / "0001.png"), np.ones((5, 5), np.uint16))
    with pytest.raises(InputError) as e:
        load_depth(folder, SHAPE)
    assert "0001.png" in str(e.value)


def test_masks(tmp_path):
    folder = tmp_path / "m"; folder.mkdir()
    for f in range(3):
        cv2.imwrite(str(folder / f"{f}.png"), np.full((10, 12), 255 if f else 0, np.uint8))
    m = load_mask(folder, SHAPE)
    assert m.dtype == np.float32 and m[0].max() == 0 and m[1].min() == 1
    with pytest.raises(InputError) as e:
        load_mask(folder, (5, 10, 12))
    assert str(folder) in str(e.value) and "5 frames" in str(e.value)
    np.save(tmp_path / "bad.npy", np.full(SHAPE, 2.0))
    with pytest.raises(InputError) as e:
        load_mask(tmp_path / "bad.npy", SHAPE)
    assert "bad.npy" in str(e.value)


def test_tracks_file(tmp_path):
    p = tmp_path / "t.npz"
    np.savez(p, xy=np.zeros((5, 3, 2), np.float32), visible=np.ones((5, 3), bool))
    t = load_tracks(p, 3)
    assert t.xy.shape == (5, 3, 2) and t.visible.all() and (t.query_frame == 0).all()
    with pytest.raises(InputError) as e:
        load_tracks(p, 4)
    assert "t.npz" in str(e.value)
    np.savez(tmp_path / "u.npz", xy=np.zeros((5, 3, 2)))
    with pytest.raises(InputError) as e:
        load_tracks(tmp_path / "u.npz", 3)
    assert "u.npz" in str(e.value) and "visible" in str(e.value)


@pytest.fixture(scope="module")
def clip():
    frames, depth, mask, K, w2c = scene.render(F=5)
    return frames, K, w2c


def _counting(monkeypatch):
    calls = {"tracks": 0, "depth": 0, "dynamic": 0, "tokens": 0}
    for name, mod, fn in (("tracks", cache_mod._tracks, "track_points"), ("depth", cache_mod._depth, "estimate_depth"),
                          ("dynamic", cache_mod._motion, "dynamic_mask"), ("tokens", cache_mod._tokens, "extract_tokens")):
        orig = getattr(mod, fn)

        def wrapped(*a, _o=orig, _n=name, **k):
            calls[_n] += 1
            return _o(*a, **k)
        monkeypatch.setattr(mod, fn, wrapped)
    return calls


def test_cache_invalidates_only_dependents(clip, tmp_path, monkeypatch):
    frames, K, w2c = clip
    calls = _counting(monkeypatch)
    cfg = PriorConfig(num_points=300)
    events = []

    class Rep:
        def progress(self, stage, step, total=None, **m):
            events.append(stage)

        def log(self, msg, level="info"):
            pass

    p1 = compute_priors(frames, K, w2c, cfg, cache_dir=tmp_path, reporter=Rep())
    # depth runs twice: a first pass for the motion mask, then without the anchors it marks
    assert calls == {"tracks": 1, "depth": 2, "dynamic": 1, "tokens": 1}
    assert {"tracks", "depth", "dynamic_mask", "priors"} <= set(events)
    p2 = compute_priors(frames, K, w2c, cfg, cache_dir=tmp_path)
    assert p2.recomputed == [] and sum(calls.values()) == 5
    assert np.array_equal(p1.depth, p2.depth) and np.array_equal(p1.tracks.xy, p2.tracks.xy)
    assert np.array_equal(p1.tokens.tokens, p2.tokens.tokens)
    compute_priors(frames, K, w2c, dataclasses.replace(cfg, patch_size=8), cache_dir=tmp_path)
    assert calls == {"tracks": 1, "depth": 2, "dynamic": 1, "tokens": 2}
    compute_priors(frames, K, w2c, dataclasses.replace(cfg, mask_width=160), cache_dir=tmp_path)
    # the mask changed: so does the second depth pass (its anchors), not the first
    assert calls == {"tracks": 1, "depth": 3, "dynamic": 2, "tokens": 2}
    p = compute_priors(frames, K, w2c, dataclasses.replace(cfg, num_points=200), cache_dir=tmp_path)
    assert calls == {"tracks": 2, "depth": 5, "dynamic": 3, "tokens": 2}
    assert sorted(p.recomputed) == ["depth", "depth_pass1", "dynamic", "tracks"]
    # another clip (different cameras) never reuses entries
    w2c2 = w2c.copy(); w2c2[:, 1, 3] += 0.01
    compute_priors(frames, K, w2c2, cfg, cache_dir=tmp_path)
    assert calls == {"tracks": 3, "depth": 7, "dynamic": 4, "tokens": 3}
    files = list((tmp_path / f"priors-v{cache_mod.CACHE_VERSION}").glob("*.npz"))
    assert files and all(not f.name.startswith(".") for f in files)


def test_precomputed_bypasses_backends(clip, tmp_path, monkeypatch):
    frames, K, w2c = clip
    F, H, W = frames.shape[:3]
    calls = _counting(monkeypatch)
    np.save(tmp_path / "depth.npy", np.full((F, H, W), 3.0, np.float32))
    np.save(tmp_path / "mask.npy", np.zeros((F, H, W), np.float32))
    cfg = PriorConfig(num_points=200, depth_path=str(tmp_path / "depth.npy"), mask_path=str(tmp_path / "mask.npy"))
    p = compute_priors(frames, K, w2c, cfg)
    assert calls["depth"] == 0 and calls["dynamic"] == 0 and np.all(p.depth == 3.0)
    np.save(tmp_path / "wrong.npy", np.zeros((F, H + 1, W), np.float32))
    with pytest.raises(InputError) as e:
        compute_priors(frames, K, w2c, dataclasses.replace(cfg, mask_path=str(tmp_path / "wrong.npy")))
    assert "wrong.npy" in str(e.value)
