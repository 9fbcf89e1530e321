"""Fused CPU SH colour (degree 0-1) for training: :func:`engine.raster.sh.sh_to_colors` in
one Numba pass with a hand-written backward.

``fused_sh_colors(means, sh_dc, sh_rest, degree, centre)`` returns
``max(SH(dir) + 0.5, 0)`` with ``dir`` the unit vector from the camera centre to each
mean, exactly the 3DGS colour of :mod:`engine.raster.sh` (same constants and basis
order), to float rounding. It reads the model's ``sh_dc`` and ``sh_rest`` as they are, so
the per-step ``torch.cat`` into ``[G, M, 3]``, the per-coefficient selects and their
backward (a zero-filled ``[G, M, 3]`` per select) disappear; the torch version is ~40
elementwise ops on ``[G, 3]`` forward and back. Degrees 2-3 keep using the torch path.

backward
    ``∂/∂sh`` = basis · (upstream gradient where ``SH + 0.5 >= 0``, as ``clamp_min``);
    ``∂/∂dir`` from the degree-1 basis, then through the normalisation
    ``dir = v / max(|v|, 1e-12)``: ``(g − dir (dir·g)) / |v|``.
Per-Gaussian, no shared writes: deterministic under any thread count.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from .fused_ssim import kernel_threads

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
C0 = np.float32(0.28209479177387814)
C1 = np.float32(0.4886025119029199)


@njit(parallel=True, **_JIT)
def _sh_forward(means, dc, rest, centre, degree, out, dirs, pre_ok):
    """``out [G, 3]`` colours; ``dirs [G, 4]`` = unit direction and |v|, ``pre_ok [G, 3]``
    = ``SH + 0.5 >= 0`` (where clamp_min passes the gradient), for the backward."""
    G = means.shape[0]
    for g in prange(G):
        vx = means[g, 0] - centre[0]
        vy = means[g, 1] - centre[1]
        vz = means[g, 2] - centre[2]
        n = np.sqrt(vx * vx + vy * vy + vz * vz)
        nc = max(n, np.float32(1e-12))
        x, y, z = vx / nc, vy / nc, vz / nc
        dirs[g, 0], dirs[g, 1], dirs[g, 2], dirs[g, 3] = x, y, z, n
        for c in range(3):
            v = C0 * dc[g, 0, c]
            if degree >= 1:
                v = v - C1 * y * rest[g, 0, c] + C1 * z * rest[g, 1, c] - C1 * x * rest[g, 2, c]
            v = v + np.float32(0.5)
            pre_ok[g, c] = v >= 0
            out[g, c] = v if v > 0 else np.float32(0.0)


@njit(parallel=True, **_JIT)
def _sh_backward(rest, degree, dirs, pre_ok, gout, g_means, g_dc, g_rest):
    G = gout.shape[0]
    for g in prange(G):
        x, y, z, n = dirs[g, 0], dirs[g, 1], dirs[g, 2], dirs[g, 3]
        gx = np.float32(0.0)
        gy = np.float32(0.0)
        gz = np.float32(0.0)
        for c in range(3):
            gv = gout[g, c] if pre_ok[g, c] else np.float32(0.0)
            g_dc[g, 0, c] = C0 * gv
            if degree >= 1:
                g_rest[g, 0, c] = -C1 * y * gv
                g_rest[g, 1, c] = C1 * z * gv
                g_rest[g, 2, c] = -C1 * x * gv
                gy -= C1 * rest[g, 0, c] * gv
                gz += C1 * rest[g, 1, c] * gv
                gx -= C1 * rest[g, 2, c] * gv
        if degree >= 1:
            if n > np.float32(1e-12):
                dot = x * gx + y * gy + z * gz
                g_means[g, 0] = (gx - x * dot) / n
                g_means[g, 1] = (gy - y * dot) / n
                g_means[g, 2] = (gz - z * dot) / n
            else:  # clamped norm: dir = v / 1e-12
                g_means[g, 0] = gx / np.float32(1e-12)
                g_means[g, 1] = gy / np.float32(1e-12)
                g_means[g, 2] = gz / np.float32(1e-12)
        else:
            g_means[g, 0] = g_means[g, 1] = g_means[g, 2] = np.float32(0.0)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _FusedSH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, sh_dc, sh_rest, degree, centre):
        G = means.shape[0]
        m, dc, rest = _np(means), _np(sh_dc), _np(sh_rest)
        if rest.shape[1] < 3:  # degree 0: the kernel never reads it
            rest = np.zeros((G, 3, 3), np.float32)
        out = np.empty((G, 3), np.float32)
        dirs = np.empty((G, 4), np.float32)
        pre_ok = np.empty((G, 3), np.bool_)
        with kernel_threads():
            _sh_forward(m, dc, rest, _np(centre.to(torch.float32)), int(degree), out, dirs, pre_ok)
        ctx.saved = (rest, dirs, pre_ok, int(degree), tuple(sh_rest.shape))
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, gout):
        rest, dirs, pre_ok, degree, rest_shape = ctx.saved
        G = pre_ok.shape[0]
        g_means = np.empty((G, 3), np.float32)
        g_dc = np.empty((G, 1, 3), np.float32)
        g_rest_full = np.zeros(rest_shape, np.float32)
        g_rest = np.empty((G, 3, 3), np.float32)
        with kernel_threads():
            _sh_backward(rest, degree, dirs, pre_ok, _np(gout.to(torch.float32)), g_means, g_dc, g_rest)
        if degree >= 1:
            g_rest_full[:, :3] = g_rest
        return (torch.from_numpy(g_means), torch.from_numpy(g_dc), torch.from_numpy(g_rest_full), None, None)


def fused_sh_colors(means: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor, degree: int,
                    w2c: torch.Tensor) -> torch.Tensor:
    """3DGS colours ``[G, 3]`` of ``means [G, 3]`` with ``sh_dc [G, 1, 3]``,
    ``sh_rest [G, M-1, 3]`` seen from camera ``w2c [4, 4]`` (degree 0 or 1, CPU float32)."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    centre = -(R.transpose(0, 1) @ t)
    return _FusedSH.apply(means, sh_dc, sh_rest, degree, centre.detach())


def fused_sh_available(degree: int, *tensors: torch.Tensor) -> bool:
    return degree <= 1 and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
