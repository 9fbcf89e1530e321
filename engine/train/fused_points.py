"""Fused CPU point terms: projected points scored against a distance map (on-mask) and
against their 2D tracks (track), each in one Numba pass with its gradient.

The training step pulls up to 4096 dynamic Gaussians onto the moving region of its frame
(:meth:`engine.train.objective.Objective.on_mask`): project, drop the points behind the
camera, sample the frame's distance map bilinearly, Huber, mean. In torch that is ~25 small
ops and their backward (~2.5 ms a step on two cores, most of it per-op overhead); here it is
one serial pass over the points in float64 (a fixed order: the result does not depend on
the thread count). The torch path stays the reference (and the GPU path):
:func:`engine.geometry.camera.project` then :func:`engine.train.losses.on_mask_loss`;
``tests/engine/test_fused_points.py`` compares values and gradients.

on_mask(points, K, w2c, dist, scale)
    ``Σ_p huber(d_p / scale, δ = 0.05) / P`` with ``d_p`` the distance map sampled at the
    point's pixel ``(u − ½, v − ½)`` (clamped to the map: ``grid_sample``'s border padding
    with aligned corners), for the points in front of the camera whose ``(u, v)`` lies in the
    image; the others count 0 but stay in ``P``. Backward: the Huber slope, the bilinear
    slope (0 along a clamped axis), the pinhole's Jacobian, then ``Rᵀ`` to world space.
track(points, K, w2c, target_uv, scale)
    :func:`engine.train.losses.track_loss` of the projected points (every point visible):
    the mean over both coordinates of ``huber((uv − target) / scale, δ = 0.05)``; the
    reference is ``project`` then ``track_loss``.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from .fused import _f32  # float32 C-contiguous NumPy view (no copy for float32 tensors)

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
HUBER_DELTA = 0.05  # on_mask_loss's


@njit(inline="always", **_JIT)
def _at(dist, y, x):
    H, W = dist.shape
    if 0 <= y < H and 0 <= x < W:
        return np.float64(dist[y, x])
    return 0.0


@njit(inline="always", **_JIT)
def _pinhole(x, p, kin, w2c):
    """Camera coordinates and pixel of point ``p``: ``(cx, cy, cz, zs, u, v)`` with ``zs`` the
    depth :func:`engine.geometry.camera.project` divides by (``|z| < 1e-12`` -> 1e-12)."""
    X, Y, Z = np.float64(x[p, 0]), np.float64(x[p, 1]), np.float64(x[p, 2])
    cx = w2c[0, 0] * X + w2c[0, 1] * Y + w2c[0, 2] * Z + w2c[0, 3]
    cy = w2c[1, 0] * X + w2c[1, 1] * Y + w2c[1, 2] * Z + w2c[1, 3]
    cz = w2c[2, 0] * X + w2c[2, 1] * Y + w2c[2, 2] * Z + w2c[2, 3]
    zs = cz if abs(cz) >= 1e-12 else 1e-12
    u = kin[0] * cx / zs + kin[1] * cy / zs + kin[2]
    v = kin[3] * cy / zs + kin[4]
    return cx, cy, cz, zs, u, v


@njit(inline="always", **_JIT)
def _pinhole_back(grad, p, gu, gv, cx, cy, cz, zs, kin, w2c):
    """``grad[p]`` = the world-space gradient of a pixel gradient ``(gu, gv)``."""
    gxn = gu * kin[0]
    gyn = gu * kin[1] + gv * kin[3]
    gcx = gxn / zs
    gcy = gyn / zs
    gcz = -(gxn * cx + gyn * cy) / (zs * zs) if abs(cz) >= 1e-12 else 0.0
    grad[p, 0] = w2c[0, 0] * gcx + w2c[1, 0] * gcy + w2c[2, 0] * gcz
    grad[p, 1] = w2c[0, 1] * gcx + w2c[1, 1] * gcy + w2c[2, 1] * gcz
    grad[p, 2] = w2c[0, 2] * gcx + w2c[1, 2] * gcy + w2c[2, 2] * gcz


@njit(inline="always", **_JIT)
def _huber(d, delta):
    """``(huber(d), slope)`` with the slope ``d`` inside ``delta`` and ``± delta`` beyond."""
    a = abs(d)
    if a < delta:
        return 0.5 * d * d, d
    return delta * (a - 0.5 * delta), (delta if d > 0.0 else -delta)


@njit(**_JIT)
def _track(x, kin, w2c, target, scale, delta, grad):
    """Value of the track term for points ``x [P, 3]`` against ``target [P, 2]`` pixels;
    ``grad [P, 3]`` (float64) gets its gradient."""
    P = x.shape[0]
    total = 0.0
    inv = 1.0 / (2 * P)
    for p in range(P):
        cx, cy, cz, zs, u, v = _pinhole(x, p, kin, w2c)
        hu, su = _huber((u - np.float64(target[p, 0])) / scale, delta)
        hv, sv = _huber((v - np.float64(target[p, 1])) / scale, delta)
        total += hu + hv
        _pinhole_back(grad, p, su / scale * inv, sv / scale * inv, cx, cy, cz, zs, kin, w2c)
    return total * inv


@njit(**_JIT)
def _on_mask(x, kin, w2c, dist, scale, delta, grad):
    """Value of the term for points ``x [P, 3]``; ``grad [P, 3]`` (float64) gets its gradient.
    ``kin [5] = fx, skew, cx, fy, cy``; ``w2c [4, 4]``; ``dist [H, W]``."""
    P = x.shape[0]
    H, W = dist.shape
    total = 0.0
    inv_p = 1.0 / P
    for p in range(P):
        grad[p, 0] = 0.0
        grad[p, 1] = 0.0
        grad[p, 2] = 0.0
        cx, cy, cz, zs, u, v = _pinhole(x, p, kin, w2c)
        if not cz > 0.0:  # behind the camera: not scored
            continue
        if not (u >= 0.0 and u < W and v >= 0.0 and v < H):
            continue
        ix = u - 0.5
        iy = v - 0.5
        gxc = 1.0 if 0.0 < ix < W - 1 else 0.0  # border padding: no slope along a clamped axis
        gyc = 1.0 if 0.0 < iy < H - 1 else 0.0
        ix = min(max(ix, 0.0), W - 1.0)
        iy = min(max(iy, 0.0), H - 1.0)
        x0 = int(np.floor(ix))
        y0 = int(np.floor(iy))
        wx = ix - x0
        wy = iy - y0
        v00, v01 = _at(dist, y0, x0), _at(dist, y0, x0 + 1)
        v10, v11 = _at(dist, y0 + 1, x0), _at(dist, y0 + 1, x0 + 1)
        s = (1.0 - wy) * ((1.0 - wx) * v00 + wx * v01) + wy * ((1.0 - wx) * v10 + wx * v11)
        h, slope = _huber(s / scale, delta)
        total += h
        gs = slope / scale * inv_p
        gu = gs * gxc * ((1.0 - wy) * (v01 - v00) + wy * (v11 - v10))
        gv = gs * gyc * ((1.0 - wx) * (v10 - v00) + wx * (v11 - v01))
        _pinhole_back(grad, p, gu, gv, cx, cy, cz, zs, kin, w2c)
    return total * inv_p


def _camera(K, w2c):
    """The kernels' camera: ``kin [5] = fx, skew, cx, fy, cy`` of ``K [3, 3]`` and ``w2c [4, 4]``,
    float64 NumPy."""
    k = K.detach().double().cpu()
    kin = np.array([float(k[0, 0]), float(k[0, 1]), float(k[0, 2]), float(k[1, 1]), float(k[1, 2])])
    return kin, w2c.detach().double().cpu().contiguous().numpy()


class _FusedPointTerm(torch.autograd.Function):
    """One point term's value (``kernel``: :func:`_track` or :func:`_on_mask`, against
    ``other``: the target pixels or the distance map); its gradient comes with the value."""

    @staticmethod
    def forward(ctx, points, K, w2c, other, scale, kernel):
        kin, view = _camera(K, w2c)
        grad = np.empty((points.shape[0], 3))
        val = kernel(_f32(points), kin, view, _f32(other), float(scale), HUBER_DELTA, grad) if len(points) else 0.0
        ctx.grad = grad
        ctx.dtype = points.dtype
        return points.new_tensor(val)

    @staticmethod
    def backward(ctx, g):
        return torch.from_numpy(ctx.grad * float(g)).to(ctx.dtype), None, None, None, None, None


def fused_track(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, target_uv: torch.Tensor,
                scale: float) -> torch.Tensor:
    """The track term of world points ``points [P, 3]`` (differentiable) against their tracks'
    pixels ``target_uv [P, 2]`` in the camera ``K``, ``w2c`` (module docstring)."""
    return _FusedPointTerm.apply(points, K, w2c, target_uv, scale, _track)


def fused_on_mask(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, dist: torch.Tensor,
                  scale: float) -> torch.Tensor:
    """The on-mask term of world points ``points [P, 3]`` (differentiable) seen by the camera
    ``K [3, 3]``, ``w2c [4, 4]`` against the distance map ``dist [H, W]`` (module docstring);
    ``scale``: pixels per unit error."""
    return _FusedPointTerm.apply(points, K, w2c, dist, scale, _on_mask)
