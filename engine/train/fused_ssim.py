"""Fused CPU SSIM: the Gaussian-window SSIM of :func:`engine.train.losses.ssim` in Numba,
with a hand-written backward.

``fused_ssim(pred, target, window, sigma)`` returns the same mean SSIM as the torch
version (separable ``window``-tap Gaussian, zero padding, 'same' size, 3DGS constants)
for ``[H, W, C]`` CPU float32 images, to float rounding. The torch version applies the
blur as dense ``[H, H]`` / ``[W, W]`` banded matrix products (~240 multiply-adds per
output where 11 are needed) plus ~30 elementwise ops and their autograd graph; here each
blur is 11 shifted, vectorised row updates and the whole loss is five passes.

forward
    products ``x, y, x², y², xy`` -> horizontal blur -> vertical blur -> per pixel
    ``S = (2 μx μy + c1)(2 σxy + c2) / ((μx² + μy² + c1)(σx² + σy² + c2))`` (float32, as the
    torch reference),
    mean over pixels and channels (per-row partial sums, then a serial sum: the result
    does not depend on the thread count).
backward
    ``∂L/∂x = blur(∂S/∂μx) + 2x · blur(∂S/∂E[x²]) + y · blur(∂S/∂E[xy])``, scaled by the
    incoming gradient over ``H·W·C``. The zero-padded Gaussian blur with a symmetric
    window is its own transpose, so the backward reuses the same two passes.

Every output element is written by one thread; there are no atomic or order-dependent
sums, so results are bit-identical run to run.
"""

from __future__ import annotations


import numpy as np
import torch
from numba import njit, prange

from ..raster.cpu import kernel_threads  # Numba at torch's thread count

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
C1, C2 = 0.01 ** 2, 0.03 ** 2


@njit(inline="always", **_JIT)
def _hblur_row(s, d, g, C):
    """``d = `` blur of row ``s [W*C]`` along W (pixel stride ``C``), zero padding.

    Written as ``len(g)`` shifted saxpys over zero-based ranges so LLVM vectorises them
    (a possibly negative index would add Numba's wrap-around check to every element).
    """
    L = s.shape[0]
    R = g.shape[0] // 2
    for l in range(L):
        d[l] = 0.0
    for k in range(g.shape[0]):
        off = (k - R) * C
        lo = max(0, -off)
        hi = min(L, L - off)
        dd = d[lo:hi]
        ss = s[lo + off:hi + off]
        wgt = g[k]
        for l in range(hi - lo):
            dd[l] += wgt * ss[l]


@njit(inline="always", **_JIT)
def _vblur_row(src, m, i, d, g):
    """``d = `` vertical blur at row ``i`` of map ``src[m] [H, L]``, zero padding."""
    H, L = src.shape[1], src.shape[2]
    R = g.shape[0] // 2
    for l in range(L):
        d[l] = 0.0
    for k in range(g.shape[0]):
        ii = i + k - R
        if ii < 0 or ii >= H:
            continue
        wgt = g[k]
        s = src[m, ii]
        for l in range(L):
            d[l] += wgt * s[l]


@njit(parallel=True, **_JIT)
def _forward_h(x, y, g, C, hb):
    """Products ``x, y, x², y², xy`` of ``x, y [H, L]`` blurred along W into ``hb [5, H, L]``."""
    H, L = x.shape
    for i in prange(H):
        p = np.empty((5, L), np.float32)
        for l in range(L):
            a, b = x[i, l], y[i, l]
            p[0, l] = a
            p[1, l] = b
            p[2, l] = a * a
            p[3, l] = b * b
            p[4, l] = a * b
        for m in range(5):
            _hblur_row(p[m], hb[m, i], g, C)


@njit(parallel=True, **_JIT)
def _forward_v(hb, g, need_grad, dmap, rowsum):
    """Vertical blur of ``hb [5, H, L]`` and SSIM per element: row sums into ``rowsum [H]``
    (float64) and, with ``need_grad``, ``dmap [3, H, L]`` = ∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy].

    The per-element maps are float32 like the torch reference (float64 here cost a third of
    the forward: its divisions do not vectorise as wide); the SSIM values go through a row
    buffer so that the element loop has no ordered float reduction (which would keep LLVM
    from vectorising it) and are summed in float64 after it."""
    _, H, L = hb.shape
    c1 = np.float32(C1)
    c2 = np.float32(C2)
    two = np.float32(2.0)
    one = np.float32(1.0)
    for i in prange(H):
        b = np.empty((6, L), np.float32)  # five blurred maps, then the row's SSIM values
        for m in range(5):
            _vblur_row(hb, m, i, b[m], g)
        for l in range(L):
            mx = b[0, l]
            my = b[1, l]
            sxx = b[2, l] - mx * mx
            syy = b[3, l] - my * my
            sxy = b[4, l] - mx * my
            a1 = two * mx * my + c1
            a2 = two * sxy + c2
            b1 = mx * mx + my * my + c1
            b2 = sxx + syy + c2
            den = b1 * b2
            sv = a1 * a2 / den
            b[5, l] = sv
            if need_grad:
                dmap[0, i, l] = two * my * (a2 - a1) / den - two * mx * sv * (one / b1 - one / b2)
                dmap[1, i, l] = -sv / b2
                dmap[2, i, l] = two * a1 / den
        acc = 0.0
        for l in range(L):
            acc += b[5, l]
        rowsum[i] = acc


@njit(parallel=True, **_JIT)
def _backward_h(dmap, g, C, hb):
    """``hb [3, H, L]`` = ``dmap`` blurred along W."""
    M, H, L = dmap.shape
    for mi in prange(M * H):
        m, i = mi // H, mi % H
        _hblur_row(dmap[m, i], hb[m, i], g, C)


@njit(parallel=True, **_JIT)
def _backward_v(hb, x, y, g, scale, out):
    """``out [H, L] = scale (blur(d0) + 2 x blur(d1) + y blur(d2))`` (vertical pass of ``hb``)."""
    _, H, L = hb.shape
    for i in prange(H):
        b = np.empty((3, L), np.float32)
        for m in range(3):
            _vblur_row(hb, m, i, b[m], g)
        for l in range(L):
            out[i, l] = scale * (b[0, l] + 2.0 * x[i, l] * b[1, l] + y[i, l] * b[2, l])


def _window(window: int, sigma: float) -> np.ndarray:
    # the float32 window of losses._gaussian_window, so both paths blur with the same taps
    x = torch.arange(window, dtype=torch.float32) - (window - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return (g / g.sum()).numpy()


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, target, window, sigma):
        h, w, c = pred.shape
        x = pred.detach().contiguous().numpy().reshape(h, w * c)
        y = target.detach().contiguous().numpy().reshape(h, w * c)
        g = _window(window, sigma)
        need = bool(ctx.needs_input_grad[0])
        hb = np.empty((5, h, w * c), np.float32)
        dmap = np.empty((3, h, w * c), np.float32) if need else np.empty((3, 1, 1), np.float32)
        rowsum = np.empty(h)
        with kernel_threads():
            _forward_h(x, y, g, c, hb)
            _forward_v(hb, g, need, dmap, rowsum)
        if need:
            ctx.saved = (x, y, g, dmap, (h, w, c))
        return pred.new_tensor(rowsum.sum() / (h * w * c))

    @staticmethod
    def backward(ctx, grad_out):
        x, y, g, dmap, (h, w, c) = ctx.saved
        hb = np.empty_like(dmap)
        out = np.empty((h, w * c), np.float32)
        scale = np.float32(float(grad_out) / (h * w * c))
        with kernel_threads():
            _backward_h(dmap, g, c, hb)
            _backward_v(hb, x, y, g, scale, out)
        return torch.from_numpy(out.reshape(h, w, c)), None, None, None


def fused_ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of ``pred, target [H, W, C]`` (CPU float32; gradient to ``pred`` only)."""
    return _FusedSSIM.apply(pred, target, window, sigma)


def fused_ssim_available(pred: torch.Tensor, target: torch.Tensor) -> bool:
    """CPU float32 images, no gradient wanted for the target."""
    return (pred.device.type == "cpu" and target.device.type == "cpu" and pred.dtype == torch.float32
            and target.dtype == torch.float32 and pred.dim() == 3 and not target.requires_grad)
