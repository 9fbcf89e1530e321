"""Exact knot insertion on cubic Hermite splines (numpy; no torch, so Blender imports it).

The curves are the ones of :mod:`engine.geometry.hermite`: between knots ``a < b`` with
``Δ = b − a`` and ``τ = (t − a)/Δ``,
``ξ(t) = h00 P_a + h10 Δ M_a^out + h01 P_b + h11 Δ M_b^in``, tangents per unit of time,
constant extrapolation (zero derivative) outside the first and last knot.

Inserting a knot ``c`` inside a segment, with the value ``ξ(c)`` and the derivative
``ξ'(c)`` as both tangents there, splits the segment's cubic into two cubics that are
the same polynomial on each side: the curve does not change. The tangents at ``a`` and
``b`` stay as they are (they are derivatives with respect to time, not to ``τ``). A knot
before the first (after the last) one takes the first (last) value with a zero
derivative, and that end knot's in-tangent (out-tangent) becomes 0, which is the
constant extrapolation on the other side of it. :func:`fill_knots` does this on a knot
grid shared by many curves, each owning a subset of the knots; the nodes' ``key_mask``
in ``nodes.npz`` records which knots are a node's own (``engine/bundle.py``).
``tests/engine/test_hermite_knots.py`` checks the results against ``hermite_eval``.
"""

from __future__ import annotations

import numpy as np


def fill_knots(times, own, values, t_out, t_in):
    """Values and tangents at the knots a curve does not own, from the knots it owns.

    Parameters
    ----------
    times : (K,) strictly increasing knot times.
    own : (..., K) bool: the knots each curve owns; every curve owns at least one.
    values, t_out, t_in : (..., K, C) float: values and out/in tangents, read only where
        ``own`` (the rest may hold anything, NaN included).

    Returns
    -------
    ``values, t_out, t_in`` (..., K, C) float64: the same curves with a knot at every
    time (see the module docstring); owned knots keep their values and tangents, except
    an in-tangent of a first owned knot (out-tangent of a last) that now has knots
    before (after) it: 0, the constant extrapolation it stood for.
    """
    times = np.asarray(times, np.float64)
    own = np.asarray(own, bool)
    k = times.shape[0]
    if own.shape[-1] != k or not own.any(axis=-1).all():
        raise ValueError("every curve must own at least one of the knots")
    vals, tout, tin = (np.asarray(a, np.float64) for a in (values, t_out, t_in))
    idx = np.broadcast_to(np.arange(k), own.shape)
    prev = np.maximum.accumulate(np.where(own, idx, -1), axis=-1)  # last owned knot at or before
    nxt = np.flip(np.minimum.accumulate(np.flip(np.where(own, idx, k), -1), axis=-1), -1)  # first at or after
    first = nxt[..., :1]
    last = prev[..., -1:]
    lo = np.where(prev < 0, first, prev)  # before the first owned knot: hold it
    hi = np.where(nxt >= k, last, nxt)  # after the last: hold it
    take = lambda a, i: np.take_along_axis(a, i[..., None], axis=-2)  # noqa: E731
    p0, m0, p1, m1 = take(vals, lo), take(tout, lo), take(vals, hi), take(tin, hi)
    ta, tb = times[lo][..., None], times[hi][..., None]
    span = tb - ta
    inner = span > 0  # strictly between two owned knots
    dt = np.where(inner, span, 1.0)
    tau = np.where(inner, (times[..., :, None] - ta) / dt, 0.0)
    t2, t3 = tau * tau, tau * tau * tau
    new_v = ((2 * t3 - 3 * t2 + 1) * p0 + (t3 - 2 * t2 + tau) * dt * m0 + (-2 * t3 + 3 * t2) * p1
             + (t3 - t2) * dt * m1)
    new_d = ((6 * t2 - 6 * tau) * p0 + (3 * t2 - 4 * tau + 1) * dt * m0 + (-6 * t2 + 6 * tau) * p1
             + (3 * t2 - 2 * tau) * dt * m1) / dt
    new_v = np.where(inner, new_v, p0)  # outside the owned range: the end value, held
    new_d = np.where(inner, new_d, 0.0)
    o = own[..., None]
    out_v = np.where(o, vals, new_v)
    out_o = np.where(o, tout, new_d)
    out_i = np.where(o, tin, new_d)
    # an end knot with filled knots beyond it: the constant extrapolation on that side
    is_first = (idx == first) & (first > 0)
    is_last = (idx == last) & (last < k - 1)
    out_i = np.where(is_first[..., None], 0.0, out_i)
    out_o = np.where(is_last[..., None], 0.0, out_o)
    return out_v, out_o, out_i


def resample_knots(key_times, times, values, t_out, t_in):
    """The curves on knots ``key_times [K]`` moved onto the knots ``times [T]`` (sorted):
    a time equal to a key time keeps that knot's values and tangents bit for bit, any
    other is an exact split (:func:`fill_knots`). Returns ``values, t_out, t_in``
    ``(..., T, C)`` float64. Knots of ``key_times`` missing from ``times`` are dropped:
    the result is the same curve only if they were splits themselves."""
    kt = np.asarray(key_times, np.float64)
    times = np.asarray(times, np.float64)
    grid = np.union1d(kt, times)
    own = np.isin(grid, kt)
    at = np.searchsorted(grid, kt)
    lead = np.shape(values)[:-2]
    c = np.shape(values)[-1]

    def place(a):
        out = np.zeros(lead + (grid.shape[0], c))
        out[..., at, :] = a
        return out

    v, o, i = fill_knots(grid, np.broadcast_to(own, lead + own.shape), place(values), place(t_out), place(t_in))
    pick = np.searchsorted(grid, times)
    return v[..., pick, :], o[..., pick, :], i[..., pick, :]
