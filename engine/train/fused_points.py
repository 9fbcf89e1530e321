"""Fused CPU on-mask term: projected points scored against a distance map, in one Numba
pass with its gradient.

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
        X, Y, Z = np.float64(x[p, 0]), np.float64(x[p, 1]), np.float64(x[p, 2])
        cx = w2c[0, 0] * X + w2c[0, 1] * Y + w2c[0, 2] * Z + w2c[0, 3]
        cy = w2c[1, 0] * X + w2c[1, 1] * Y + w2c[1, 2] * Z + w2c[1, 3]
        cz = w2c[2, 0] * X + w2c[2, 1] * Y + w2c[2, 2] * Z + w2c[2, 3]
        if not cz > 0.0:  # behind the camera: not scored
            continue
        zs = cz if cz >= 1e-12 else 1e-12
        xn = cx / zs
        yn = cy / zs
        u = kin[0] * xn + kin[1] * yn + kin[2]
        v = kin[3] * yn + kin[4]
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
        d = s / scale
        if d < delta:
            total += 0.5 * d * d
            slope = d
        else:
            total += delta * (d - 0.5 * delta)
            slope = delta
        gs = slope / scale * inv_p
        gu = gs * gxc * ((1.0 - wy) * (v01 - v00) + wy * (v11 - v10))
        gv = gs * gyc * ((1.0 - wx) * (v10 - v00) + wx * (v11 - v01))
        gxn = gu * kin[0]
        gyn = gu * kin[1] + gv * kin[3]
        gcx = gxn / zs
        gcy = gyn / zs
        gcz = -(gxn * cx + gyn * cy) / (zs * zs) if cz >= 1e-12 else 0.0
        grad[p, 0] = w2c[0, 0] * gcx + w2c[1, 0] * gcy + w2c[2, 0] * gcz
        grad[p, 1] = w2c[0, 1] * gcx + w2c[1, 1] * gcy + w2c[2, 1] * gcz
        grad[p, 2] = w2c[0, 2] * gcx + w2c[1, 2] * gcy + w2c[2, 2] * gcz
    return total * inv_p


class _FusedOnMask(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, K, w2c, dist, scale):
        k = K.detach().double().cpu()
        kin = np.array([float(k[0, 0]), float(k[0, 1]), float(k[0, 2]), float(k[1, 1]), float(k[1, 2])])
        grad = np.empty((points.shape[0], 3))
        val = _on_mask(_f32(points), kin, w2c.detach().double().cpu().contiguous().numpy(), _f32(dist),
                       float(scale), HUBER_DELTA, grad)
        ctx.grad = grad
        ctx.dtype = points.dtype
        return points.new_tensor(val)

    @staticmethod
    def backward(ctx, g):
        return torch.from_numpy(ctx.grad * float(g)).to(ctx.dtype), None, None, None, None


def fused_on_mask(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, dist: torch.Tensor,
                  scale: float) -> torch.Tensor:
    """The on-mask term of world points ``points [P, 3]`` (differentiable) seen by the camera
    ``K [3, 3]``, ``w2c [4, 4]`` against the distance map ``dist [H, W]`` (module docstring);
    ``scale``: pixels per unit error."""
    return _FusedOnMask.apply(points, K, w2c, dist, scale)
