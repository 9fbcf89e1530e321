"""Loss terms of the composite objective (paper Sec. 'Optimization').

All functions are torch, differentiable, and document their shapes. Images are
``[H, W, C]`` float in [0, 1]. :func:`ssim` runs the fused Numba kernel of
:mod:`.fused_ssim` on CPU float32 images (same value to float rounding, a few times
cheaper); :func:`ssim_torch` is the reference and the GPU path.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def l1(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error; ``weight`` broadcasts against ``pred`` ([H, W, 1] masks)."""
    err = (pred - target).abs()
    if weight is None:
        return err.mean()
    w = weight.expand_as(err)
    return (err * w).sum() / w.sum().clamp_min(1e-8)


#: box-downsampling factors of :func:`coarse_l1` (px at the training width)
COARSE_POOLS = (4, 8)


def coarse_l1(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
              pools: tuple[int, ...] = COARSE_POOLS) -> torch.Tensor:
    """Mean L1 between box-downsampled images, averaged over the factors ``pools``.

    Why: a moving object rendered a few pixels off its place in the frame pays, at full
    resolution, mostly the mismatch of its pixel-scale texture, which is already there at a
    one-pixel offset; the part of the cost (and of the gradient) that says *how far off* it is
    comes from its silhouette edges only. Downsampled by ``k`` the texture averages out and the
    object's silhouette and mean colour remain, whose L1 grows with the offset up to about the
    object's size (``tests/engine/test_losses_terms.py``: 6 px cost 5x 1 px, against 2x at
    full resolution): a steadier pull of the nodes toward the object, at no extra render.

    Parameters
    ----------
    pred, target : [H, W, 3]; weight : [H, W, 1] or None, pooled like the images (a weighted
    mean over the downsampled pixels); pools : downsampling factors (``ceil_mode``: the
    border cells average what they cover).
    """
    a, b = pred.permute(2, 0, 1).unsqueeze(0), target.permute(2, 0, 1).unsqueeze(0)
    w = None if weight is None else weight.expand(*pred.shape[:2], 1).permute(2, 0, 1).unsqueeze(0)
    total = pred.new_zeros(())
    for k in pools:
        err = (F.avg_pool2d(a, k, ceil_mode=True) - F.avg_pool2d(b, k, ceil_mode=True)).abs()
        if w is None:
            total = total + err.mean()
        else:
            wk = F.avg_pool2d(w, k, ceil_mode=True).expand_as(err)
            total = total + (err * wk).sum() / wk.sum().clamp_min(1e-8)
    return total / len(pools)


def _gaussian_window(size: int, sigma: float, device, dtype) -> torch.Tensor:
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


_BLUR_CACHE: dict = {}


def _blur_matrices(h: int, w: int, window: int, sigma: float, device, dtype):
    """Banded matrices ``Gy [H, H]`` and ``Gxᵀ [W, W]`` with ``Gy @ img @ Gxᵀ`` equal to the
    separable ``window``-tap Gaussian filter with zero padding ('same' size)."""
    key = (h, w, window, float(sigma), str(device), dtype)
    mats = _BLUR_CACHE.get(key)
    if mats is None:
        g = _gaussian_window(window, sigma, device, dtype)
        pad = window // 2

        def band(n):
            i = torch.arange(n, device=device)
            off = i[None, :] - i[:, None] + pad  # out row i, input column j -> tap j - i + pad
            ok = (off >= 0) & (off < window)
            return torch.where(ok, g[off.clamp(0, window - 1)], torch.zeros((), device=device, dtype=dtype))

        mats = (band(h), band(w).T.contiguous())
        if len(_BLUR_CACHE) > 16:
            _BLUR_CACHE.clear()
        _BLUR_CACHE[key] = mats
    return mats


#: use engine/train/fused_ssim.py for CPU float32 images (tests switch it off to compare)
FUSED_SSIM = True


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean structural similarity of two ``[H, W, C]`` images (Gaussian window, as in 3DGS).

    CPU float32 images without a target gradient go through the fused Numba kernel
    (:mod:`.fused_ssim`); everything else through :func:`ssim_torch`.
    """
    if FUSED_SSIM:
        try:
            from .fused_ssim import fused_ssim, fused_ssim_available
        except ImportError:  # no numba: the torch path
            pass
        else:
            if fused_ssim_available(pred, target):
                return fused_ssim(pred, target, window, sigma)
    return ssim_torch(pred, target, window, sigma)


def ssim_torch(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean structural similarity of two ``[H, W, C]`` images (Gaussian window, as in 3DGS).

    Uses a separable Gaussian filter with zero padding ('same' size) like the 3DGS
    reference, so values match what papers report (applied as banded-matrix products,
    which on the CPU is several times cheaper than depthwise convolutions).
    """
    c = pred.shape[-1]
    x = pred.permute(2, 0, 1).unsqueeze(0)
    y = target.permute(2, 0, 1).unsqueeze(0)
    h, w = x.shape[-2:]
    gy, gx_t = _blur_matrices(h, w, window, sigma, pred.device, pred.dtype)

    def blur(img):  # separable Gaussian blur with zero padding as two small matmuls
        return gy @ (img @ gx_t)

    # blurs of the prediction terms (x, x², xy) in one stacked call; the target-only
    # ones (y, y²) in another, outside autograd when the target needs no gradient
    mu_x, bxx, bxy = blur(torch.cat([x, x * x, x * y], dim=1)).split(c, dim=1)
    with torch.set_grad_enabled(torch.is_grad_enabled() and target.requires_grad):
        mu_y, byy = blur(torch.cat([y, y * y], dim=1)).split(c, dim=1)
    sxx = bxx - mu_x * mu_x
    syy = byy - mu_y * mu_y
    sxy = bxy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    return (num / den).mean()


def photometric(pred: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2,
                weight: torch.Tensor | None = None, l1_value: torch.Tensor | None = None) -> torch.Tensor:
    """3DGS photometric loss ``(1 - λ) L1 + λ (1 - SSIM)``; images ``[H, W, 3]``.

    ``weight [H, W, 1]`` (optional) makes the L1 term a weighted mean over pixels;
    ``l1_value``: that L1 when the caller already has it (the training step's fused pass)."""
    loss = (1.0 - ssim_weight) * (l1(pred, target, weight) if l1_value is None else l1_value)
    if ssim_weight > 0:
        loss = loss + ssim_weight * (1.0 - ssim(pred, target))
    return loss


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1]; optional ``[H, W, 1]`` mask."""
    err = (pred - target) ** 2
    if mask is None:
        mse = err.mean()
    else:
        w = mask.expand_as(err)
        mse = (err * w).sum() / w.sum().clamp_min(1e-8)
    return psnr_from_mse(mse)


def psnr_from_mse(mse: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of images in [0, 1] from their mean squared error (floored at 1e-12)."""
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


def depth_shift_scale_invariant(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Depth loss invariant to an affine map of the target (MiDaS-style).

    Solves ``min_{s,b} ||s·target + b − pred||²`` in closed form over valid pixels (no
    gradient through ``s, b``), then returns the mean absolute residual relative to the
    median predicted depth, so the loss is scale-free.

    Parameters
    ----------
    pred : (H, W) rendered expected depth.
    target : (H, W) prior depth (any affine-equivalent scale).
    valid : (H, W) bool, pixels where both are meaningful.
    """
    with torch.no_grad():
        # the fit and the median need the valid values; the differentiable part below is a
        # dense masked mean, so autograd never scatters back through a boolean gather
        p, t = pred.detach()[valid], target[valid]
        n = p.numel()
        if n < 16:
            return pred.sum() * 0.0
        scale, shift = _affine_fit(t, p)
        aligned = scale * target + shift
        norm = p.median().clamp_min(1e-6)
        weight = valid.to(pred.dtype) / (n * norm)  # mean over valid pixels, / median depth
    return ((pred - aligned).abs() * weight).sum()


def _affine_fit(t: torch.Tensor, p: torch.Tensor) -> tuple[float, float]:
    """``argmin_{s,b} Σ (s t + b − p)²`` for ``t, p [n]``, from the 2x2 normal equations in
    float64 (deterministic, unlike ``torch.linalg.lstsq`` on the CPU, which reads
    uninitialised memory once torch no longer NaN-fills allocations -- see the trainer)."""
    t64, p64 = t.double(), p.double()
    return affine_from_sums(float(t64.numel()), float(t64.sum()), float(p64.sum()), float((t64 * t64).sum()),
                            float((t64 * p64).sum()))


def affine_from_sums(n: float, st: float, sp: float, stt: float, stp: float) -> tuple[float, float]:
    """``(s, b)`` of the least-squares line ``p ≈ s t + b`` from the sums ``n, Σt, Σp, Σt²,
    Σtp``. A constant ``t`` gets the least-norm solution, as a rank-revealing solver would."""
    det = n * stt - st * st
    if det <= 1e-12 * max(n * stt, 1e-300):
        c, m = st / n, sp / n
        return c * m / (c * c + 1.0), m / (c * c + 1.0)
    return (n * stp - st * sp) / det, (stt * sp - st * stp) / det


def mask_loss(alpha: torch.Tensor, dyn_alpha: torch.Tensor, fg_prior: torch.Tensor) -> torch.Tensor:
    """Mask term: the alpha rendered from dynamic Gaussians should match the fg prior.

    Parameters
    ----------
    alpha : (H, W, 1) total rendered alpha (unused weight; kept for API symmetry).
    dyn_alpha : (H, W, 1) the per-Gaussian dynamic score composited like a colour (the
        trainer renders it as the colour pass's ``extra`` channel).
    fg_prior : (H, W) dynamic/foreground prior in [0, 1].
    """
    return F.binary_cross_entropy(dyn_alpha.squeeze(-1).clamp(1e-4, 1 - 1e-4), fg_prior.clamp(0, 1))


def track_loss(proj_uv: torch.Tensor, target_uv: torch.Tensor, visible: torch.Tensor, scale: float) -> torch.Tensor:
    """Mean Huber distance between projected positions and 2D tracks.

    Parameters
    ----------
    proj_uv, target_uv : (P, 2) pixels.
    visible : (P,) bool.
    scale : pixels per unit error (e.g. image width), so the loss is resolution-free.
    """
    if visible.sum() == 0:
        return proj_uv.sum() * 0.0
    d = (proj_uv[visible] - target_uv[visible]) / scale
    return F.huber_loss(d, torch.zeros_like(d), delta=0.05, reduction="mean")


def mask_distance(fg: torch.Tensor, threshold: float) -> torch.Tensor:
    """Distance in px from every pixel to the nearest moving pixel, per frame.

    Parameters
    ----------
    fg : (F, H, W) dynamic prior in [0, 1]; ``>= threshold`` is moving.

    Returns
    -------
    (F, H, W) float32 on ``fg``'s device: 0 on moving pixels; frames without a moving pixel
    are all 0 (no information where the moving things are).
    """
    import cv2
    import numpy as np

    moving = (fg >= threshold).cpu().numpy()
    out = np.zeros(moving.shape, np.float32)
    for f in np.flatnonzero(moving.reshape(len(moving), -1).any(1)):  # one OpenCV call per frame
        out[f] = cv2.distanceTransform((~moving[f]).astype(np.uint8), cv2.DIST_L2, 5)
    return torch.from_numpy(out).to(fg.device)


def on_mask_loss(uv: torch.Tensor, dist: torch.Tensor, scale: float) -> torch.Tensor:
    """How far projected points lie outside the moving region: mean Huber of the distance map.

    Parameters
    ----------
    uv : (P, 2) projected positions in pixels (continuous coordinates).
    dist : (H, W) distance to the nearest moving pixel (:func:`mask_distance`).
    scale : pixels per unit error (as :func:`track_loss`).

    Points outside the image count 0 (objects leave the frame) but stay in the mean's
    denominator. The distance is sampled bilinearly between pixel centres (``dist[r, c]`` sits
    at ``(c + 0.5, r + 0.5)``), so its gradient points towards the region from as far away as
    the point is.
    """
    h, w = dist.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not bool(inside.any()):
        return uv.sum() * 0.0
    p = uv[inside] - 0.5  # pixel-centre coordinates
    grid = torch.stack([p[:, 0] / max(w - 1, 1) * 2 - 1, p[:, 1] / max(h - 1, 1) * 2 - 1], -1).view(1, -1, 1, 2)
    d = F.grid_sample(dist.view(1, 1, h, w).to(uv.dtype), grid, align_corners=True,
                      padding_mode="border").view(-1) / scale
    return F.huber_loss(d, torch.zeros_like(d), delta=0.05, reduction="sum") / uv.shape[0]


def arap_loss(pos_t0: torch.Tensor, pos_t1: torch.Tensor, rot_t1: torch.Tensor, graph_idx: torch.Tensor,
              graph_w: torch.Tensor | None = None) -> torch.Tensor:
    """As-rigid-as-possible on the node graph between two times.

    For each node ``i`` and neighbour ``j``, the edge ``p_j − p_i`` at ``t1`` should be the
    edge at ``t0`` rotated by node ``i``'s relative rotation ``R_i(t1)``:
    ``|| (p_j(t1) − p_i(t1)) − R_i (p_j(t0) − p_i(t0)) ||²``.

    Parameters
    ----------
    pos_t0, pos_t1 : (N, 3) node positions at two times.
    rot_t1 : (N, 3, 3) node rotations at t1 relative to t0.
    graph_idx : (N, k) neighbour indices.
    graph_w : (N, k) optional edge weights.
    """
    e0 = pos_t0[graph_idx] - pos_t0[:, None, :]
    e1 = pos_t1[graph_idx] - pos_t1[:, None, :]
    r = e0 @ rot_t1.transpose(-1, -2)  # R_i e0_ij for all j: one [k, 3] x [3, 3] product per node
    err = ((e1 - r) ** 2).sum(-1)
    if graph_w is not None:
        return (err * graph_w).sum() / graph_w.sum().clamp_min(1e-8)
    return err.mean()


def arap_states(pos_t0: torch.Tensor, rot_t0: torch.Tensor, pos_t1: torch.Tensor, rot_t1: torch.Tensor,
                graph_idx: torch.Tensor) -> torch.Tensor:
    """:func:`arap_loss` between two node states given as positions ``[N, 3]`` and
    quaternions ``[N, 4]`` (normalised here): the relative rotation of node ``i`` is
    ``R(q̂1_i) R(q̂0_i)ᵀ``. The reference of :func:`engine.train.fused_reg.fused_arap`."""
    from ..geometry.quaternion import quat_normalize, quat_to_matrix

    rel = quat_to_matrix(quat_normalize(rot_t1)) @ quat_to_matrix(quat_normalize(rot_t0)).transpose(-1, -2)
    return arap_loss(pos_t0, pos_t1, rel, graph_idx)


def static_motion_keys(pos_keys: torch.Tensor, rot_keys: torch.Tensor, weight: torch.Tensor, arm: torch.Tensor,
                       extent: float, ref_pos: torch.Tensor | None = None,
                       ref_rot: torch.Tensor | None = None) -> torch.Tensor:
    """Motion energy of keyed node trajectories: ``mean_i w_i (Var_k p_ik / extent² +
    arm_i Var_k q̂_ik)`` (variances over the keys, summed over the components; a mean over
    the nodes like ARAP and the smoothness terms, so its weight does not grow with the
    node count).

    Parameters
    ----------
    pos_keys : (N, K, 3), rot_keys : (N, K, 4) spline / per-frame keys (rotations are
        normalised here).
    weight, arm : (N,) per-node weight and rotation arm (constants).
    extent : scene extent (positions are measured in its units).
    ref_pos : (N, K, 3), ref_rot : (N, K, 4), optional constants subtracted from the keys
        and the normalised rotations first (the trainer's ``static_init`` reference).

    The reference of :func:`engine.train.fused_reg.fused_key_terms`.
    """
    from ..geometry.quaternion import quat_normalize

    pk, q = pos_keys, quat_normalize(rot_keys)
    if ref_pos is not None:
        pk = pk - ref_pos
    if ref_rot is not None:
        q = q - ref_rot
    pk = pk / extent
    e = ((pk - pk.mean(1, keepdim=True)) ** 2).sum(-1).mean(1)
    e = e + ((q - q.mean(1, keepdim=True)) ** 2).sum(-1).mean(1) * arm
    return (weight * e).mean()


def spline_smoothness(keys: torch.Tensor, key_times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Velocity and acceleration energies of spline keys.

    Parameters
    ----------
    keys : (N, K, C) spline keys.
    key_times : (K,) key times.

    Returns
    -------
    velocity, acceleration : scalars, mean squared first/second finite differences in
    key-time units.
    """
    if keys.shape[1] < 2:
        zero = keys.sum() * 0.0
        return zero, zero
    dt = (key_times[1:] - key_times[:-1]).clamp_min(1e-6)
    vel = (keys[:, 1:] - keys[:, :-1]) / dt[None, :, None]
    v = (vel ** 2).mean()
    if keys.shape[1] < 3:
        return v, keys.sum() * 0.0
    dtm = 0.5 * (dt[1:] + dt[:-1])
    acc = (vel[:, 1:] - vel[:, :-1]) / dtm[None, :, None]
    return v, (acc ** 2).mean()
