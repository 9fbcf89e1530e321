"""Cubic Hermite splines over non-uniform key times (the node trajectories).

Shapes: ``key_times [K]`` strictly increasing; ``keys``/``tangents`` ``[..., K, C]``
(any leading batch dims, ``C`` channels: 3 for positions, 4 for quaternions);
tangents are derivatives per unit of time. Evaluation times ``t [T]``.

Between keys ``k`` and ``k+1`` with ``Δ = t_{k+1} − t_k`` and ``τ = (t − t_k)/Δ``::

    ξ(t) = h00(τ) P_k + h10(τ) Δ M_k + h01(τ) P_{k+1} + h11(τ) Δ M_{k+1}

Outside ``[t_0, t_{K−1}]`` the curve is held constant at the end key (Blender's default
"constant extrapolation"), with zero derivative.
"""

from __future__ import annotations

import numpy as np
import torch


def hermite_basis(tau: torch.Tensor):
    """Hermite basis ``(h00, h10, h01, h11)`` at ``tau`` (any shape)."""
    t2 = tau * tau
    t3 = t2 * tau
    return 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + tau, -2 * t3 + 3 * t2, t3 - t2


def _hermite_basis_deriv(tau: torch.Tensor):
    t2 = tau * tau
    return 6 * t2 - 6 * tau, 3 * t2 - 4 * tau + 1, -6 * t2 + 6 * tau, 3 * t2 - 2 * tau


def catmull_rom_tangents(key_times: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
    """Non-uniform Catmull-Rom (central finite-difference) tangents.

    Interior: ``(P_{k+1} − P_{k−1}) / (t_{k+1} − t_{k−1})``; ends: one-sided
    ``(P_1 − P_0)/(t_1 − t_0)`` and ``(P_{K−1} − P_{K−2})/(t_{K−1} − t_{K−2})``.
    A single key gets a zero tangent. Linear in ``keys``.

    Parameters
    ----------
    key_times : (K,)
    keys : (..., K, C)

    Returns
    -------
    (..., K, C) tangents per unit time.
    """
    k = keys.shape[-2]
    if k < 2:
        return torch.zeros_like(keys)
    kt = key_times.to(keys)  # dtype and device of the keys
    first = (keys[..., 1:2, :] - keys[..., 0:1, :]) / (kt[1] - kt[0])
    last = (keys[..., -1:, :] - keys[..., -2:-1, :]) / (kt[-1] - kt[-2])
    if k == 2:
        return torch.cat([first, last], dim=-2)
    interior = (keys[..., 2:, :] - keys[..., :-2, :]) / (kt[2:] - kt[:-2]).unsqueeze(-1)
    return torch.cat([first, interior, last], dim=-2)


def hermite_eval(key_times: torch.Tensor, keys: torch.Tensor, tangents: torch.Tensor, t: torch.Tensor,
                 tangents_in: torch.Tensor | None = None, derivative: bool = False):
    """Evaluate many Hermite curves at many times.

    Parameters
    ----------
    key_times : (K,) strictly increasing.
    keys : (..., K, C) values at the keys.
    tangents : (..., K, C) outgoing tangents (per unit time).
    t : (T,) query times; clamped to ``[t_0, t_{K−1}]`` (constant extrapolation).
    tangents_in : (..., K, C), optional
        Incoming tangents when they differ from the outgoing ones (broken Bézier
        handles); segment ``k`` uses ``tangents[k]`` and ``tangents_in[k+1]``.
    derivative : bool
        Also return ``dξ/dt``.

    Returns
    -------
    values : (..., T, C)
    deriv : (..., T, C), only when ``derivative`` is true (zero outside the key range).
    """
    t = torch.as_tensor(t, dtype=keys.dtype, device=keys.device).reshape(-1)
    kt = key_times.to(keys)  # dtype and device of the keys
    k = kt.shape[0]
    if k == 1:
        vals = keys.expand(keys.shape[:-2] + (t.shape[0], keys.shape[-1]))
        return (vals, torch.zeros_like(vals)) if derivative else vals
    tin = tangents if tangents_in is None else tangents_in
    tc = t.clamp(kt[0], kt[-1])
    seg = (torch.searchsorted(kt, tc, right=True) - 1).clamp(0, k - 2)  # [T]
    t0 = kt[seg]
    dt = kt[seg + 1] - t0
    tau = ((tc - t0) / dt).unsqueeze(-1)  # [T, 1]
    p0 = keys[..., seg, :]
    p1 = keys[..., seg + 1, :]
    m0 = tangents[..., seg, :] * dt.unsqueeze(-1)
    m1 = tin[..., seg + 1, :] * dt.unsqueeze(-1)
    h00, h10, h01, h11 = hermite_basis(tau)
    vals = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
    if not derivative:
        return vals
    d00, d10, d01, d11 = _hermite_basis_deriv(tau)
    inside = ((t >= kt[0]) & (t <= kt[-1])).to(keys.dtype).unsqueeze(-1)
    deriv = (d00 * p0 + d10 * m0 + d01 * p1 + d11 * m1) / dt.unsqueeze(-1) * inside
    return vals, deriv


def hermite_eval_quat(key_times, keys, tangents, t, tangents_in=None):
    """Per-channel Hermite evaluation of quaternion keys, then normalisation.

    This is exactly what Blender does with four ``rotation_quaternion`` F-curves.
    Returns ``(..., T, 4)`` unit quaternions.
    """
    from .quaternion import quat_normalize

    return quat_normalize(hermite_eval(key_times, keys, tangents, t, tangents_in))


def hermite_basis_matrix(key_times: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Matrix ``B [T, K]`` with ``ξ(t) = B @ keys`` when tangents are Catmull-Rom.

    Catmull-Rom tangents are linear in the keys, so the whole spline is; evaluating the
    spline of the identity "keys" gives the basis.
    """
    k = key_times.shape[0]
    eye = torch.eye(k, dtype=key_times.dtype, device=key_times.device)
    keys = eye.unsqueeze(-1)  # [K curves, K keys, 1]: curve j has keys e_j
    vals = hermite_eval(key_times, keys, catmull_rom_tangents(key_times, keys), t)  # [K(curves), T, 1]
    return vals[..., 0].T.contiguous()


def difference_matrix(k: int, order: int = 1, dtype=torch.float32, device=None) -> torch.Tensor:
    """Finite-difference operator ``D [K−order, K]`` over keys (order 1: velocity,
    rows ``(−1, 1)``; order 2: acceleration, rows ``(1, −2, 1)``)."""
    d = torch.eye(k, dtype=dtype, device=device)
    for _ in range(order):
        d = d[1:] - d[:-1]
    return d


def hermite_fit(key_times: torch.Tensor, t: torch.Tensor, samples: torch.Tensor,
                weights: torch.Tensor | None = None, smoothness: float = 0.0,
                fallback: torch.Tensor | None = None, ridge: float = 1e-6,
                curvature: float = 0.0) -> torch.Tensor:
    """Weighted least-squares keys of a Catmull-Rom Hermite spline through samples.

    Solves, per curve,
    ``min_P Σ_s w_s ||B(t_s) P − x_s||² + λ ||D₁ P||² + μ ||D₂ P||² + ε ||P − P_fb||²``
    with ``D₁``/``D₂`` first/second differences of the keys (``λ = smoothness`` keeps
    poorly observed curves *still* instead of extrapolating a trend; ``μ = curvature``
    only penalises bending) and a tiny ridge
    ``ε = ridge · (1 + mean diag(BᵀWB))`` towards ``fallback`` keys, so curves with few
    or no samples are well defined: with no samples at all the result is ``fallback``
    (default: the curve's weighted sample mean, or zero when it has none).

    Parameters
    ----------
    key_times : (K,)
    t : (S,) sample times.
    samples : (..., S, C); NaN entries are missing (weight 0 for that sample).
    weights : (..., S), optional non-negative sample weights.
    smoothness : float, λ (velocity penalty).
    curvature : float, μ (acceleration penalty).
    fallback : (..., K, C), optional.

    Returns
    -------
    keys : (..., K, C); tangents follow from :func:`catmull_rom_tangents`.
    """
    dtype = samples.dtype
    t = torch.as_tensor(t, dtype=dtype, device=samples.device)
    kt = key_times.to(samples)  # dtype and device of the samples
    B = hermite_basis_matrix(kt, t)  # [S, K]
    valid = torch.isfinite(samples).all(-1)  # [..., S]
    w = valid.to(dtype) if weights is None else weights.to(dtype) * valid.to(dtype)
    x = torch.where(torch.isfinite(samples), samples, torch.zeros((), dtype=dtype, device=samples.device))
    A = torch.einsum("sk,...s,sl->...kl", B, w, B)  # [..., K, K]
    rhs = torch.einsum("sk,...s,...sc->...kc", B, w, x)  # [..., K, C]
    k = kt.shape[0]
    if fallback is None:
        wsum = w.sum(-1, keepdim=True)  # [..., 1]
        mean = (w.unsqueeze(-1) * x).sum(-2) / wsum.clamp_min(1e-12)  # [..., C]
        fallback = mean.unsqueeze(-2).expand(rhs.shape)
    eps = ridge * (1.0 + torch.diagonal(A, dim1=-2, dim2=-1).mean(-1))  # [...]
    eye = torch.eye(k, dtype=dtype, device=samples.device)
    D1 = difference_matrix(k, 1, dtype, samples.device)
    D2 = difference_matrix(k, 2, dtype, samples.device)
    M = A + smoothness * (D1.T @ D1) + curvature * (D2.T @ D2) + eps[..., None, None] * eye
    rhs = rhs + eps[..., None, None] * fallback
    return torch.linalg.solve(M, rhs)


def catmull_rom_basis(key_times: np.ndarray, t: float) -> np.ndarray:
    """Weights ``b [K]`` (float64) of the keys in the Catmull-Rom Hermite spline at ``t``.

    Mirrors :func:`hermite_eval` with :func:`catmull_rom_tangents` written as a fixed linear
    map of the keys, ``x(t) = Σ_k b_k P_k``: ``t`` clamped to the key range (constant
    extrapolation), segment ``seg`` with ``t_seg <= t < t_seg+1``, and tangents
    ``M_k = Σ_j C_kj P_j`` (one-sided at the ends, central inside).
    """
    k = key_times.shape[0]
    b = np.zeros(k)
    if k == 1:
        b[0] = 1.0
        return b
    tc = min(max(t, key_times[0]), key_times[-1])
    seg = min(max(int(np.searchsorted(key_times, tc, side="right")) - 1, 0), k - 2)
    t0, dt = key_times[seg], key_times[seg + 1] - key_times[seg]
    tau = (tc - t0) / dt
    t2, t3 = tau * tau, tau * tau * tau
    h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + tau, -2 * t3 + 3 * t2, t3 - t2

    def tangent_row(i):  # C[i] : M_i = Σ_j C[i, j] P_j
        row = np.zeros(k)
        lo, hi = (0, 1) if i == 0 else ((k - 2, k - 1) if i == k - 1 else (i - 1, i + 1))
        row[hi] += 1.0 / (key_times[hi] - key_times[lo])
        row[lo] -= 1.0 / (key_times[hi] - key_times[lo])
        return row

    b[seg] += h00
    b[seg + 1] += h01
    b += dt * (h10 * tangent_row(seg) + h11 * tangent_row(seg + 1))
    return b
