"""Weighted rigid fits of point sets (batched Kabsch), torch.

Used to give nodes the rotation of the points they carry (node initialisation from lifted
tracks); the numpy fits of camera poses live in :mod:`.poses`.
"""

from __future__ import annotations

import torch


def weighted_kabsch(src: torch.Tensor, dst: torch.Tensor, weight: torch.Tensor, min_points: int = 3,
                    min_spread: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched weighted rigid fit ``dst ≈ R · src + t``.

    Minimises ``Σ_n w_n |R src_n + t − dst_n|²`` per batch element (Kabsch with weights;
    proper rotations only, ``det R = +1``). Samples with ``w_n = 0`` or non-finite points
    are ignored.

    Parameters
    ----------
    src, dst : (..., P, 3) corresponding points (NaN allowed where a sample is missing).
    weight : (..., P) non-negative weights.
    min_points : int
        Fewer usable samples than this -> not ``ok``.
    min_spread : float
        The fit is ``ok`` only where the weighted ``src`` spread has a second principal
        standard deviation of at least ``min_spread`` times its first (collinear points
        leave the rotation about their line free).

    Returns
    -------
    R : (..., 3, 3) rotation (the identity where not ``ok``).
    t : (..., 3) translation (weighted centroid difference where not ``ok``; zero without samples).
    ok : (..., ) bool.
    """
    usable = torch.isfinite(src).all(-1) & torch.isfinite(dst).all(-1) & (weight > 0)
    w = torch.where(usable, weight, torch.zeros_like(weight))
    s = torch.where(usable.unsqueeze(-1), src, torch.zeros_like(src))
    d = torch.where(usable.unsqueeze(-1), dst, torch.zeros_like(dst))
    wsum = w.sum(-1, keepdim=True).clamp_min(1e-12)  # [..., 1]
    ms = (w.unsqueeze(-1) * s).sum(-2) / wsum  # [..., 3]
    md = (w.unsqueeze(-1) * d).sum(-2) / wsum
    xs, xd = s - ms.unsqueeze(-2), d - md.unsqueeze(-2)
    cov = torch.einsum("...p,...pi,...pj->...ij", w, xd, xs)  # Σ w (dst)(src)ᵀ, [..., 3, 3]
    U, S, Vh = torch.linalg.svd(cov)
    det = torch.linalg.det(U @ Vh)
    D = torch.ones_like(S)
    D[..., 2] = torch.where(det < 0, -1.0, 1.0).to(S)
    R = U @ torch.diag_embed(D) @ Vh
    # spread of the source points alone decides whether the rotation is determined
    src_cov = torch.einsum("...p,...pi,...pj->...ij", w, xs, xs)
    ev = torch.linalg.eigvalsh(src_cov)  # ascending
    spread_ok = ev[..., 1].clamp_min(0).sqrt() >= min_spread * ev[..., 2].clamp_min(0).sqrt()
    ok = (usable.sum(-1) >= min_points) & spread_ok & (ev[..., 2] > 0)
    eye = torch.eye(3, dtype=R.dtype, device=R.device).expand_as(R)
    R = torch.where(ok[..., None, None], R, eye)
    t = md - (R @ ms.unsqueeze(-1)).squeeze(-1)
    return R, t, ok
