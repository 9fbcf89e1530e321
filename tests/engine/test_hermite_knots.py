"""Exact knot insertion (engine/geometry/hermite_knots.py) against hermite_eval: a curve
with knots filled in where it owns none evaluates to the same curve, everywhere."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.geometry.hermite import hermite_eval
from engine.geometry.hermite_knots import fill_knots, resample_knots


def _eval(times, v, o, i, query):
    return hermite_eval(torch.tensor(times), torch.tensor(v), torch.tensor(o), torch.tensor(query),
                        tangents_in=torch.tensor(i), derivative=True)


def test_filled_knots_leave_every_curve_unchanged():
    rng = np.random.default_rng(0)
    times = np.sort(rng.uniform(-0.2, 1.2, 9))
    n, c = 40, 4
    own = rng.uniform(size=(n, 9)) < 0.5
    own[np.arange(n), rng.integers(0, 9, n)] = True  # every curve owns a knot
    own[0] = [False, False, True, False, True, False, False, False, False]  # held on both sides
    own[1] = True
    vals = rng.normal(size=(n, 9, c))
    t_out, t_in = rng.normal(size=(n, 9, c)), rng.normal(size=(n, 9, c))
    v, o, i = fill_knots(times, own, np.where(own[..., None], vals, np.nan), t_out, t_in)
    assert np.isfinite(v).all() and np.isfinite(o).all() and np.isfinite(i).all()
    query = np.linspace(times[0] - 0.3, times[-1] + 0.3, 301)
    for row in range(n):
        kt = times[own[row]]
        ref = _eval(kt, vals[row, own[row]], t_out[row, own[row]], t_in[row, own[row]], query)
        got = _eval(times, v[row], o[row], i[row], query)
        np.testing.assert_allclose(got[0].numpy(), ref[0].numpy(), atol=1e-10, err_msg=f"row {row}")
        inside = (query > kt[0]) & (query < kt[-1])  # the derivative too, away from the held ends
        np.testing.assert_allclose(got[1].numpy()[inside], ref[1].numpy()[inside], atol=1e-9)
        # owned knots keep their values bit for bit
        assert np.array_equal(v[row, own[row]], vals[row, own[row]])
    assert np.array_equal(o[1], t_out[1]) and np.array_equal(i[1], t_in[1])  # owns all: untouched


def test_resample_keeps_shared_knots_and_splits_the_rest():
    rng = np.random.default_rng(1)
    kt = np.linspace(0, 1, 6)
    vals, t_out, t_in = (rng.normal(size=(5, 6, 3)).astype(np.float32) for _ in range(3))
    times = np.sort(np.concatenate([kt, [0.37, 0.9]]))
    v, o, i = resample_knots(kt, times, vals, t_out, t_in)
    at = np.searchsorted(times, kt)
    assert np.array_equal(v[:, at].astype(np.float32), vals) and np.array_equal(o[:, at].astype(np.float32), t_out)
    query = np.linspace(0, 1, 101)
    np.testing.assert_allclose(_eval(times, v, o, i, query)[0].numpy(),
                               _eval(kt, vals.astype(np.float64), t_out.astype(np.float64),
                                     t_in.astype(np.float64), query)[0].numpy(), atol=1e-12)


def test_a_curve_must_own_a_knot():
    with pytest.raises(ValueError):
        fill_knots(np.arange(3.0), np.zeros((1, 3), bool), np.zeros((1, 3, 1)), np.zeros((1, 3, 1)),
                   np.zeros((1, 3, 1)))


def test_the_engine_moves_gaussians_alike_with_a_split_knot(tmp_path):
    """What Send Edits writes when one Empty is keyed at a new frame: the other nodes get a
    split knot (key_mask False). The engine's consumers of nodes.npz (model_from_bundle:
    render, export, eval, finetune) read it as an ordinary knot; the motion is unchanged."""
    from engine import bundle as B
    from engine.train.from_bundle import model_from_bundle

    from .test_bundle import _gaussians, _nodes

    nodes = _nodes(n=7, k=5, g=50)
    scene = B.new_scene(1, 25, 24.0, cameras=[{"w2c": np.eye(4), "K": np.eye(3), "width": 8, "height": 6,
                                                 "time": 0.5}])
    B.save_bundle(tmp_path / "a", scene, nodes, _gaussians())
    kt = np.sort(np.concatenate([nodes.key_times, [0.4375]]))
    arrays = nodes.to_dict()
    arrays["key_times"] = kt
    for name in ("pos", "rot"):
        out = getattr(nodes, f"{name}_tangents")
        v, o, i = resample_knots(nodes.key_times, kt, getattr(nodes, f"{name}_keys"), out, out)
        arrays[f"{name}_keys"], arrays[f"{name}_tangents"] = v, o
        assert np.array_equal(o, i)
    arrays["key_mask"] = np.isin(kt, nodes.key_times)[None].repeat(7, 0)
    B.save_bundle(tmp_path / "b", scene, B.NodeArrays.from_dict(arrays), _gaussians())
    ma, mb = (model_from_bundle(B.load_bundle(tmp_path / x), "cpu") for x in "ab")
    for t in np.linspace(0, 1, 17):
        xa, qa = ma.deform(float(t))
        xb, qb = mb.deform(float(t))
        torch.testing.assert_close(xb, xa, atol=2e-5, rtol=0)
        torch.testing.assert_close(qb, qa, atol=2e-5, rtol=0)
