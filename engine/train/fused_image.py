"""Fused CPU image terms: the per-pixel parts of the training loss that are not SSIM, each
value computed in one Numba pass together with its gradient.

At the preview size (240x180) the torch versions of these terms are ~40 small ops and as
many in the backward -- about 6 ms of a ~75 ms step on two cores, most of it per-op
overhead and passes over the image. Here each is one or two passes. Sums are per-row
float64 partials added serially, so the results do not depend on the thread count. The
torch versions stay the references (and the CUDA path): :func:`engine.train.losses.l1`,
:func:`engine.train.losses.coarse_l1`, :func:`engine.train.losses.psnr` and
:func:`engine.train.losses.depth_shift_scale_invariant`; ``tests/engine/test_fused_image.py``
checks values and gradients against them.

l1_terms(pred, target, weight, pools)
    ``(l1, coarse, mse)``: the ``weight``-weighted mean absolute error, the mean over the
    factors ``pools`` of the weighted L1 between box-downsampled images (``ceil_mode``
    cells, each averaging what it covers; a cell's weight is its mean pixel weight), and
    the mean squared error of ``clamp(pred, 0, 1)`` (for the PSNR metric; no gradient).
    Backward: ``sign(e) w / Σw`` per pixel plus, per pool, the cell's ``sign(ē) w̄ / Σw̄``
    over its pixel count.
depth_term(depth_sum, alpha, prior)
    The shift/scale-invariant depth loss of the rendered expected depth
    ``depth_sum / max(alpha, 1e-6)`` against ``prior`` over the pixels with ``prior > 0``
    and ``alpha > 0.5``: the closed-form affine fit and the (lower) median are constants,
    so the gradient to ``depth_sum`` is ``sign(r) / (n · median · max(alpha, 1e-6))``.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ..raster.cpu import kernel_threads  # Numba at torch's thread count
from .fused import _f32, fused_available  # _f32: float32 C-contiguous NumPy view (no copy)
from .losses import affine_from_sums

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)


@njit(inline="always", **_JIT)
def _sign(v):
    return _F1 if v > _F0 else (-_F1 if v < _F0 else _F0)


@njit(parallel=True, **_JIT)
def _pixel_rows(x, y, w, rows):
    """``x, y [H, W, C]``, ``w [H, W]``: per row ``Σ |x − y| w``, ``Σ w`` and
    ``Σ (clamp(x, 0, 1) − y)²`` into ``rows [H, 3]`` (float64)."""
    H, W, C = x.shape
    for i in prange(H):
        sa = 0.0
        sw = 0.0
        sq = 0.0
        for j in range(W):
            wj = w[i, j]
            sw += wj
            for c in range(C):
                a = x[i, j, c]
                b = y[i, j, c]
                sa += abs(a - b) * wj
                d = min(max(a, _F0), _F1) - b
                sq += d * d
        rows[i, 0] = sa
        rows[i, 1] = sw * C
        rows[i, 2] = sq


@njit(parallel=True, **_JIT)
def _cell_rows(x, y, w, k, cell, rows):
    """Box-downsampled L1 at factor ``k``: per cell ``(ē, w̄)`` with ``ē = mean_cell x −
    mean_cell y`` per channel, ``w̄`` the cell's mean weight; ``cell [Hc, Wc, C]`` gets
    ``sign(ē) w̄ / count`` (the unnormalised gradient of each of the cell's pixels), ``rows
    [Hc, 2]`` the row sums of ``|ē| w̄`` and ``C w̄`` (float64). Each band of ``k`` rows is
    first summed down its columns (contiguous reads), then along each cell's columns."""
    H, W, C = x.shape
    Hc, Wc = cell.shape[0], cell.shape[1]
    for ci in prange(Hc):
        y0, y1 = ci * k, min(H, ci * k + k)
        col = np.zeros((W, C), np.float32)  # Σ_rows (x - y): the cell sum of x - y is all ē needs
        colw = np.zeros(W, np.float32)
        for yy in range(y0, y1):
            for j in range(W):
                colw[j] += w[yy, j]
                for c in range(C):
                    col[j, c] += x[yy, j, c] - y[yy, j, c]
        se = 0.0
        sw = 0.0
        for cj in range(Wc):
            x0, x1 = cj * k, min(W, cj * k + k)
            inv = 1.0 / ((y1 - y0) * (x1 - x0))
            wsum = 0.0
            for j in range(x0, x1):
                wsum += colw[j]
            wbar = wsum * inv
            sw += wbar * C
            for c in range(C):
                e = 0.0
                for j in range(x0, x1):
                    e += col[j, c]
                e *= inv
                se += abs(e) * wbar
                cell[ci, cj, c] = np.float32((1.0 if e > 0.0 else (-1.0 if e < 0.0 else 0.0)) * wbar * inv)
        rows[ci, 0] = se
        rows[ci, 1] = sw


@njit(parallel=True, **_JIT)
def _l1_backward(x, y, w, s_l1, cells, ks, s_cells, out):
    """``out [H, W, C] = s_l1 sign(x − y) w + Σ_p s_cells[p] cells[p][i // k_p, j // k_p]``
    (``cells`` a tuple of the per-pool cell maps, ``ks`` their factors)."""
    H, W, C = x.shape
    for i in prange(H):
        o = out[i]
        for j in range(W):
            wj = w[i, j] * s_l1
            for c in range(C):
                d = x[i, j, c] - y[i, j, c]
                o[j, c] = (np.float32(d > _F0) - np.float32(d < _F0)) * wj
        for p in range(len(ks)):
            k = ks[p]
            cp = cells[p][i // k]
            sp = s_cells[p]
            for cj in range(cp.shape[0]):
                for c in range(C):
                    v = sp * cp[cj, c]
                    for j in range(cj * k, min(W, cj * k + k)):
                        o[j, c] += v


class _FusedL1Terms(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, target, weight, pools):
        x, y = _f32(pred), _f32(target)
        H, W, C = x.shape
        w = np.ones((H, W), np.float32) if weight is None else _f32(weight.reshape(H, W))
        rows = np.empty((H, 3))
        cells, s_cells, coarse = [], [], 0.0
        with kernel_threads():
            _pixel_rows(x, y, w, rows)
            for k in pools:
                cell = np.empty((-(-H // k), -(-W // k), C), np.float32)
                crow = np.empty((cell.shape[0], 2))
                _cell_rows(x, y, w, int(k), cell, crow)
                norm = max(float(crow[:, 1].sum()), 1e-8)
                coarse += float(crow[:, 0].sum()) / norm
                cells.append(cell)
                s_cells.append(1.0 / (norm * len(pools)))
        norm1 = max(float(rows[:, 1].sum()), 1e-8)
        ctx.state = (x, y, w, 1.0 / norm1, tuple(cells), tuple(int(k) for k in pools), s_cells)
        ctx.dtype = pred.dtype
        mse = pred.new_tensor(float(rows[:, 2].sum()) / x.size)
        ctx.mark_non_differentiable(mse)
        return pred.new_tensor(float(rows[:, 0].sum()) / norm1), pred.new_tensor(coarse / max(len(pools), 1)), mse

    @staticmethod
    def backward(ctx, g_l1, g_coarse, _g_mse):
        x, y, w, s1, cells, ks, s_cells = ctx.state
        a = 0.0 if g_l1 is None else float(g_l1)
        b = 0.0 if g_coarse is None else float(g_coarse)
        out = np.empty_like(x)
        if not cells:  # numba cannot type an empty tuple of arrays: one inert pool
            cells, ks, s_cells = (np.zeros((1, 1, x.shape[2]), np.float32),), (x.shape[0] + x.shape[1],), [0.0]
        with kernel_threads():
            _l1_backward(x, y, w, np.float32(a * s1), cells, ks,
                         np.array([b * s for s in s_cells], np.float32), out)
        return torch.from_numpy(out).to(ctx.dtype), None, None, None


def fused_l1_terms(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
                   pools: tuple[int, ...] = ()) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(l1, coarse, mse)`` of ``pred, target [H, W, C]`` (see the module docstring);
    ``weight [H, W, 1]`` or None; ``coarse`` is 0 without ``pools``. Gradient to ``pred``."""
    return _FusedL1Terms.apply(pred, target, weight, tuple(pools))


@njit(parallel=True, **_JIT)
def _depth_rows(dsum, alpha, prior, depth, rows):
    """Expected depth ``depth = dsum / max(alpha, 1e-6)`` where valid (``prior > 0``,
    ``alpha > 0.5``; +inf elsewhere, so that invalid pixels sort last) and per row the fit's
    sums ``n, Σt, Σp, Σt², Σtp`` (float64) into ``rows [H, 5]``."""
    H, W = dsum.shape
    for i in prange(H):
        n = 0.0
        st = 0.0
        sp = 0.0
        stt = 0.0
        stp = 0.0
        for j in range(W):
            a = alpha[i, j]
            t = prior[i, j]
            if t > _F0 and a > np.float32(0.5):
                p = dsum[i, j] / max(a, np.float32(1e-6))
                depth[i, j] = p
                tt = np.float64(t)
                pp = np.float64(p)
                n += 1.0
                st += tt
                sp += pp
                stt += tt * tt
                stp += tt * pp
            else:
                depth[i, j] = np.inf
        rows[i, 0] = n
        rows[i, 1] = st
        rows[i, 2] = sp
        rows[i, 3] = stt
        rows[i, 4] = stp


@njit(parallel=True, **_JIT)
def _depth_residual(depth, alpha, prior, scale, shift, wgt, grad, rows):
    """``rows [H] = Σ |depth − (scale prior + shift)| wgt`` over the valid pixels (finite
    ``depth``), ``grad [H, W] = sign(r) wgt / max(alpha, 1e-6)`` there and 0 elsewhere."""
    H, W = depth.shape
    for i in prange(H):
        acc = 0.0
        for j in range(W):
            p = depth[i, j]
            if p < np.inf:
                r = p - (scale * prior[i, j] + shift)
                acc += abs(r) * wgt
                grad[i, j] = _sign(r) * wgt / max(alpha[i, j], np.float32(1e-6))
            else:
                grad[i, j] = _F0
        rows[i] = acc


class _FusedDepthTerm(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth_sum, alpha, prior):
        ds, al, pr = _f32(depth_sum), _f32(alpha), _f32(prior)
        H, W = ds.shape
        depth = np.empty((H, W), np.float32)
        rows = np.empty((H, 5))
        with kernel_threads():
            _depth_rows(ds, al, pr, depth, rows)
        n, st, sp, stt, stp = (float(v) for v in rows.sum(0))
        ctx.dtype = depth_sum.dtype
        if n < 16:
            ctx.grad = None
            return depth_sum.new_zeros(())
        scale, shift = affine_from_sums(n, st, sp, stt, stp)
        k = (int(n) - 1) // 2  # torch.median: the lower of the two middle values
        norm = max(float(np.partition(depth.reshape(-1), k)[k]), 1e-6)
        wgt = np.float32(1.0) / (np.float32(n) * np.float32(norm))
        grad = np.empty((H, W), np.float32)
        res = np.empty(H)
        with kernel_threads():
            _depth_residual(depth, al, pr, np.float32(scale), np.float32(shift), wgt, grad, res)
        ctx.grad = grad
        return depth_sum.new_tensor(float(res.sum()))

    @staticmethod
    def backward(ctx, g):
        if ctx.grad is None:
            return None, None, None
        return torch.from_numpy(ctx.grad * np.float32(float(g))).to(ctx.dtype), None, None


def fused_depth_term(depth_sum: torch.Tensor, alpha: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """The depth term of ``depth_sum, alpha, prior [H, W]`` (module docstring); gradient to
    ``depth_sum`` only (``alpha`` is a constant of the term, as in the reference)."""
    return _FusedDepthTerm.apply(depth_sum, alpha.detach(), prior)


def fused_image_available(*tensors: torch.Tensor) -> bool:
    """What every fused pass handles (:func:`~engine.train.fused.fused_available`: CPU float32),
    with no tensor but the first wanting a gradient (these passes differentiate only it)."""
    return fused_available(*tensors) and not any(t.requires_grad for t in tensors[1:])
