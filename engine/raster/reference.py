"""Reference backend: plain, readable PyTorch; any device, any float dtype.

This is the correctness oracle for the fast backends. It is written for clarity, not
speed: compositing is *dense* (every Gaussian is evaluated at every pixel, memory
``O(H*W*N)``), so use it on small scenes only.

Semantics (shared by every backend, see :mod:`engine.raster`):

* EWA projection with the Jacobian's ``x/z, y/z`` clamped to 1.3x the field of view (as in
  3DGS/gsplat), plus a ``eps2d = 0.3`` px low-pass added to the 2D covariance diagonal.
* A Gaussian is *visible* if ``near < z < far``, the 2D covariance is positive definite,
  ``opacity >= 1/255`` and its footprint (the ellipse where ``alpha >= 1/255``) overlaps
  the image.
* Per pixel, Gaussians are composited front to back in order of camera depth ``z`` of
  their means (ties: lower index first). ``alpha = min(0.99, o * exp(-sigma))`` with
  ``sigma = 0.5 d^T conic d`` and ``d = pixel_centre - mean2d``; contributions with
  ``sigma < 0`` or ``alpha < 1/255`` are skipped. Early termination: the first Gaussian
  that would take the transmittance below ``1e-4`` is *not* composited and the pixel
  stops there (original 3DGS rule).
"""

from __future__ import annotations


import torch

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
EPS2D = 0.3
# elements of one dense [pixels, Gaussians] temporary in rasterize (~64 MB in float32)
DENSE_BUDGET = 1 << 24


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[N, 3, 3]`` from quaternions ``[N, 4]`` (wxyz, normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def project(means, quats, scales, opacities, w2c, K, width, height, near=0.01, far=1e4, eps2d=EPS2D):
    """EWA-project 3D Gaussians to the image.

    Parameters
    ----------
    means [N, 3], quats [N, 4] (wxyz, any norm), scales [N, 3] (linear), opacities [N]
    w2c [4, 4] : world-to-camera, OpenCV axes.
    K [3, 3] : intrinsics, continuous pixel coordinates (pixel centre at +0.5).
    width, height : int
    near, far : float
        Depth range for the *means*.

    Returns
    -------
    means2d [N, 2], conics [N, 3] (upper triangle ``a, b, c`` of the inverse 2D
    covariance), depths [N] (camera z), radii [N] int32 (``ceil(3 sigma_max)``, 0 when not
    visible), extents [N, 2] (half-width/height in px of the ``alpha >= 1/255`` box, 0 when
    not visible; not differentiable).
    Everything but radii/extents is differentiable; invisible rows hold garbage-free but
    meaningless values and must be ignored via ``radii > 0``.
    """
    dtype = means.dtype
    R = w2c[:3, :3].to(dtype)
    t = w2c[:3, 3].to(dtype)
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item()
    in_range = (z > near) & (z < far)
    zs = torch.where(in_range, z, torch.ones_like(z))  # keeps invisible rows finite

    Rq = quat_to_rotmat(quats)
    M = Rq * scales[:, None, :]
    cov3 = M @ M.transpose(1, 2)
    covc = R @ cov3 @ R.T

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    tx = zs * torch.clamp(x / zs, -lim_xn, lim_xp)
    ty = zs * torch.clamp(y / zs, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs),
                     zero, fy / zs, -fy * ty / (zs * zs)], dim=-1).reshape(-1, 2, 3)
    cov2 = J @ covc @ J.transpose(1, 2)
    a = cov2[:, 0, 0] + eps2d
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = in_range & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        o = opacities.detach().to(dtype)
        ok = ok & (o >= ALPHA_MIN)
        thr = torch.log((255.0 * o).clamp_min(1.0))
        ex = torch.sqrt(2.0 * thr * a.clamp_min(0)) * 1.0001 + 0.01
        ey = torch.sqrt(2.0 * thr * c.clamp_min(0)) * 1.0001 + 0.01
        u, v = means2d.detach().unbind(-1)
        ok = ok & (u + ex > 0) & (u - ex < width) & (v + ey > 0) & (v - ey < height)
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
        radii = torch.where(ok, torch.ceil(3.0 * torch.sqrt(lam.clamp_min(0))), torch.zeros_like(lam))
        radii = radii.to(torch.int32)
        extents = torch.where(ok[:, None], torch.stack([ex, ey], -1), torch.zeros_like(means2d))
    return means2d, conics, z, radii, extents


def rasterize(means2d, conics, depths, colors, opacities, visible, width, height, background=None, extra=None):
    """Dense front-to-back compositing (the oracle).

    Parameters
    ----------
    means2d [N, 2], conics [N, 3], depths [N], colors [N, 3], opacities [N]
    visible [N] bool : Gaussians to composite (``radii > 0``).
    background [3] or None (black).
    extra [N] or None : a per-Gaussian scalar composited like a colour channel with no
        background; not differentiated itself (detached).

    Returns
    -------
    rgb [H, W, 3], alpha [H, W, 1], depth [H, W, 1] (``sum_i w_i z_i``, *not* divided by
    alpha), final transmittance [H, W, 1]; with ``extra`` also its image [H, W, 1] (a fifth
    value).
    """
    dtype, dev = means2d.dtype, means2d.device
    idx = torch.nonzero(visible, as_tuple=False).flatten()
    order = idx[torch.sort(depths.detach()[idx], stable=True).indices]
    m2, cn, dz = means2d[order], conics[order], depths[order]
    col, op = colors[order], opacities[order]
    if extra is not None:  # one more colour channel; the background gets a 0 for it
        col = torch.cat([col, extra.detach().to(col)[order, None]], 1)
        if background is not None:
            background = torch.cat([background.to(col), torch.zeros(1, dtype=col.dtype, device=col.device)])
    # pixels are independent: composite bands of rows so the dense [pixels, n] temporaries
    # stay near DENSE_BUDGET elements (a full 240x180 frame of 30k Gaussians would be 5 GB each)
    band = max(1, min(height, DENSE_BUDGET // max(1, len(order) * width)))
    outs = [_composite_rows(m2, cn, dz, col, op, y0, min(height, y0 + band), width, background)
            for y0 in range(0, height, band)]
    rgb, alpha, depth, T_final = (torch.cat(parts, 0) for parts in zip(*outs))
    if extra is not None:
        return rgb[..., :3], alpha, depth, T_final, rgb[..., 3:]
    return rgb, alpha, depth, T_final


def _composite_rows(m2, cn, dz, col, op, y0: int, y1: int, width: int, background):
    """:func:`rasterize` for image rows ``y0 <= y < y1`` (Gaussians already depth-sorted);
    returns rgb [h, W, 3], alpha, depth, transmittance [h, W, 1] with h = y1 - y0."""
    dtype, dev = m2.dtype, m2.device
    height = y1 - y0
    ys, xs = torch.meshgrid(torch.arange(y0, y1, device=dev, dtype=dtype) + 0.5,
                            torch.arange(width, device=dev, dtype=dtype) + 0.5, indexing="ij")
    dx = xs.reshape(-1, 1) - m2[None, :, 0]  # [P, n]
    dy = ys.reshape(-1, 1) - m2[None, :, 1]
    sigma = 0.5 * (cn[None, :, 0] * dx * dx + cn[None, :, 2] * dy * dy) + cn[None, :, 1] * dx * dy
    alpha = torch.clamp(op[None, :] * torch.exp(-sigma), max=ALPHA_MAX)
    keep = (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T_after = torch.cumprod(one_minus, dim=1)
    # Early termination: a Gaussian is composited only while the transmittance *after*
    # it stays >= T_MIN. T_after is non-increasing, so this is a prefix of each row.
    live = (T_after >= T_MIN).detach()
    alpha = torch.where(live, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1.0 - alpha, dim=1)
    ones = torch.ones(T_after.shape[0], 1, dtype=dtype, device=dev)
    T_before = torch.cat([ones, T_after[:, :-1]], dim=1)
    w = alpha * T_before
    T_final = T_after[:, -1:] if T_after.shape[1] else ones
    rgb = w @ col
    if background is not None:
        rgb = rgb + T_final * background.to(dtype)
    depth = w @ dz[:, None]
    return (rgb.reshape(height, width, col.shape[1]), (1.0 - T_final).reshape(height, width, 1),
            depth.reshape(height, width, 1), T_final.reshape(height, width, 1))
