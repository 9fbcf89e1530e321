"""Real spherical harmonics (degrees 0-3) for view-dependent colour, in torch.

Shared by every backend: the colour of each Gaussian is evaluated here, before the
rasteriser, so the kernels only ever see ``colors [N, 3]`` and autograd handles the SH
backward. Constants and basis ordering follow the original 3DGS code (and gsplat), so
PLY files written by :mod:`engine.bundle` render the same in common splat viewers.
"""

from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree``: ``(degree + 1) ** 2``."""
    return (degree + 1) ** 2


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH colour.

    Parameters
    ----------
    degree : int
        SH degree in ``0..3``; only the first ``(degree+1)**2`` coefficients are used.
    sh : Tensor [N, M, 3]
        Coefficients, ``M >= (degree+1)**2``; index 0 is the DC term.
    dirs : Tensor [N, 3]
        Unit view directions (camera centre -> Gaussian), world frame.

    Returns
    -------
    Tensor [N, 3]
        Raw SH value (no +0.5 offset, no clamping).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    if sh.shape[-2] < num_sh_bases(degree):
        raise ValueError(f"sh has {sh.shape[-2]} coefficients, degree {degree} needs {num_sh_bases(degree)}")
    out = C0 * sh[:, 0]
    if degree == 0:
        return out
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    out = out - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
    if degree == 1:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (out + C2[0] * xy * sh[:, 4] + C2[1] * yz * sh[:, 5] + C2[2] * (2 * zz - xx - yy) * sh[:, 6]
           + C2[3] * xz * sh[:, 7] + C2[4] * (xx - yy) * sh[:, 8])
    if degree == 2:
        return out
    return (out + C3[0] * y * (3 * xx - yy) * sh[:, 9] + C3[1] * xy * z * sh[:, 10]
            + C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + C3[5] * z * (xx - yy) * sh[:, 14]
            + C3[6] * x * (xx - 3 * yy) * sh[:, 15])


def sh_to_colors(sh: torch.Tensor, degree: int, means: torch.Tensor, w2c: torch.Tensor) -> torch.Tensor:
    """3DGS colour: ``max(SH(dir) + 0.5, 0)`` with ``dir`` from the camera centre to each mean.

    Parameters
    ----------
    sh : Tensor [N, M, 3]
    degree : int
    means : Tensor [N, 3]
        World positions.
    w2c : Tensor [4, 4]
        World-to-camera (OpenCV axes); the camera centre is ``-R^T t``.

    Returns
    -------
    Tensor [N, 3]
    """
    R, t = w2c[:3, :3], w2c[:3, 3]
    centre = -(R.transpose(0, 1) @ t)
    d = means - centre.to(means.dtype)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return (eval_sh(degree, sh, d) + 0.5).clamp_min(0.0)
