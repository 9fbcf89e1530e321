"""``cpu`` backend: torch.autograd.Functions around the Numba kernels in :mod:`.cpu_numba`.

Two Functions, like gsplat: :class:`ProjectCPU` (3D -> 2D) and :class:`RasterizeCPU`
(2D -> image). ``means2d`` is a real intermediate tensor, so training can call
``means2d.retain_grad()`` and read the 2D-mean gradient for densification.

Threads: Numba runs with ``torch.get_num_threads()`` threads (the process's count, set once
where it starts: ``engine/runtime.py``). Torch's own thread count is never changed here: it
used to be dropped to one around every kernel because torch's spinning OpenMP pool stalled
Numba's, which ``OMP_WAIT_POLICY=PASSIVE`` (``engine/__main__.py``, the benches) settles;
an A/B of the train bench found the same CPU time per step either way (docs/benchmarks.md).
"""

from __future__ import annotations

import contextlib

import numba
import numpy as np
import torch

from . import cpu_numba as K_
from .cpu_numba import TILE
from .reference import EPS2D


@contextlib.contextmanager
def kernel_threads():
    """Run the Numba kernels inside with torch's thread count (``numba.set_num_threads``
    applies to the calling thread only; no process-wide state changes)."""
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    yield


def _np(t: torch.Tensor) -> np.ndarray:
    """float32, C-contiguous NumPy view of ``t`` (a copy only when dtype/layout/device differ)."""
    if t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous():
        return t.detach().numpy()
    return t.detach().to(device="cpu", dtype=torch.float32).contiguous().numpy()


def _intr(K) -> np.ndarray:
    k = K.detach().cpu().double().numpy()
    return np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], np.float32)


def _as(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    """``a`` as a tensor of ``dtype`` (no copy when it already is float32 and so is dtype)."""
    t = torch.from_numpy(a)
    return t if t.dtype == dtype else t.to(dtype)


class ProjectCPU(torch.autograd.Function):
    """(means, quats, scales, opacities) -> (means2d, conics, depths, radii, extents)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, w2c, K, width, height, near, far):
        n = means.shape[0]
        m, q, s, o = _np(means), _np(quats), _np(scales), _np(opacities)
        view, intr = _np(w2c), _intr(K)
        # project_forward writes every entry
        means2d = np.empty((n, 2), np.float32)
        conics = np.empty((n, 3), np.float32)
        depths = np.empty(n, np.float32)
        radii = np.empty(n, np.int32)
        extents = np.empty((n, 2), np.float32)
        with kernel_threads():
            K_.dynamic(K_.project_forward, K_.PROJ_CHUNK, m, q, s, o, view, intr, int(width), int(height),
                       np.float32(near), np.float32(far), np.float32(EPS2D), means2d, conics, depths, radii, extents)
        ctx.save_for_backward(means, quats, scales)
        ctx.view, ctx.intr, ctx.size, ctx.radii = view, intr, (int(width), int(height)), radii
        r, e = torch.from_numpy(radii), torch.from_numpy(extents)
        ctx.mark_non_differentiable(r, e)
        return torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), r, e

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _r, _e):
        means, quats, scales = ctx.saved_tensors
        n = means.shape[0]
        z = lambda t, shape: np.zeros(shape, np.float32) if t is None else _np(t)  # noqa: E731
        v_m = np.empty((n, 3), np.float32)
        v_q = np.empty((n, 4), np.float32)
        v_s = np.empty((n, 3), np.float32)
        with kernel_threads():
            K_.dynamic(K_.project_backward, K_.PROJ_CHUNK, _np(means), _np(quats), _np(scales), ctx.view, ctx.intr,
                       ctx.size[0], ctx.size[1], np.float32(EPS2D), ctx.radii, z(v_means2d, (n, 2)),
                       z(v_conics, (n, 3)), z(v_depths, (n,)), v_m, v_q, v_s)
        return (_as(v_m, means.dtype), _as(v_q, quats.dtype), _as(v_s, scales.dtype), None, None, None, None, None,
                None, None)


class RasterizeCPU(torch.autograd.Function):
    """(means2d, conics, depths, colors, opacities[, extra]) -> (rgb [H,W,3], alpha [H,W,1],
    depth [H,W,1], extra image [H,W,E]) with E = 1 when ``extra [N]`` is given, else 0.

    The extra channel is composited like a colour without background and is not
    differentiated itself; its image's gradient reaches the geometry and opacities. It
    runs in the same pass as the colour (the ``*_extra`` kernel variants), so a
    per-Gaussian scalar such as a dynamic score costs one more channel, not a second render.
    """

    @staticmethod
    def forward(ctx, means2d, conics, depths, colors, opacities, radii, extents, width, height, background,
                extra=None):
        W, H = int(width), int(height)
        tx, ty = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
        n = means2d.shape[0]
        m2, cn, dz = _np(means2d), _np(conics), _np(depths)
        col, op = _np(colors), _np(opacities)
        bg = np.zeros(3, np.float32) if background is None else _np(background)
        rgb = np.empty((H, W, 3), np.float32)
        dep = np.empty((H, W), np.float32)
        T = np.empty((H, W), np.float32)
        last = np.empty((H, W), np.int32)
        xe = extra is not None
        ex_img = np.empty((H, W) if xe else (0, 0), np.float32)
        with kernel_threads():
            offsets, gid, data, idata, gstart = K_.bin_tiles(dz, m2, cn, col, op, _np(extents), radii.numpy(),
                                                             W, H, tx, ty, _np(extra) if xe else None)
            K_.tile_loop(K_.raster_forward_extra if xe else K_.raster_forward, offsets, data, idata, W, H, tx, bg,
                         rgb, dep, T, last, ex_img)
        ctx.state = (offsets, data, idata, gstart, bg, T, last, W, H, tx, n, xe)
        ctx.dtypes = (means2d.dtype, conics.dtype, depths.dtype, colors.dtype, opacities.dtype)
        ctx.has_bg = background is not None
        ctx.bg_dtype = None if background is None else background.dtype
        alpha = torch.from_numpy(1.0 - T)[..., None]
        ctx.n_instances = int(gid.shape[0])
        return torch.from_numpy(rgb), alpha, torch.from_numpy(dep)[..., None], torch.from_numpy(ex_img)[..., None]

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_extra):
        offsets, data, idata, gstart, bg, T, last, W, H, tx, n, xe = ctx.state
        gr = np.zeros((H, W, 3), np.float32) if g_rgb is None else _np(g_rgb)
        ga = np.zeros((H, W), np.float32) if g_alpha is None else _np(g_alpha[..., 0])
        gd = np.zeros((H, W), np.float32) if g_depth is None else _np(g_depth[..., 0])
        if xe:
            ge = np.zeros((H, W), np.float32) if g_extra is None else _np(g_extra[..., 0])
        else:
            ge = np.empty((0, 0), np.float32)
        # per-Gaussian gradients, each its own contiguous array (no strided views downstream)
        v_m2 = np.empty((n, 2), np.float32)
        v_cn = np.empty((n, 3), np.float32)
        v_op = np.empty(n, np.float32)
        v_col = np.empty((n, 3), np.float32)
        v_dz = np.empty(n, np.float32)
        with kernel_threads():
            grads = K_.pooled("grads", data.shape[0] * 10, np.float32).reshape(-1, 10)
            inst = K_.tile_loop(K_.raster_backward_extra if xe else K_.raster_backward, offsets, data, idata, W, H,
                                tx, bg, T, last, gr, ga, gd, ge, grads)
            K_.sum_instances(gstart, K_.instance_bounds(gstart, numba.get_num_threads()), inst, v_m2, v_cn, v_op,
                             v_col, v_dz)
        d = ctx.dtypes
        v_bg = None
        if ctx.has_bg and ctx.needs_input_grad[9]:
            v_bg = (torch.from_numpy(gr) * torch.from_numpy(T)[..., None]).sum((0, 1)).to(ctx.bg_dtype)
        return (_as(v_m2, d[0]), _as(v_cn, d[1]), _as(v_dz, d[2]), _as(v_col, d[3]), _as(v_op, d[4]),
                None, None, None, None, v_bg, None)


def project(means, quats, scales, opacities, w2c, K, width, height, near=0.01, far=1e4):
    """Same contract as :func:`engine.raster.reference.project` (CPU tensors, float32 math)."""
    return ProjectCPU.apply(means, quats, scales, opacities, w2c, K, width, height, near, far)


def rasterize(means2d, conics, depths, colors, opacities, radii, extents, width, height, background=None,
              extra=None):
    """Tile compositing; returns ``rgb [H,W,3], alpha [H,W,1], depth [H,W,1]`` and, with
    ``extra [N]``, its composited image ``[H,W,1]`` (else None)."""
    rgb, alpha, depth, ex = RasterizeCPU.apply(means2d, conics, depths, colors, opacities, radii, extents, width,
                                               height, background, extra)
    return rgb, alpha, depth, (ex if extra is not None else None)
