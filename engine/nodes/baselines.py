"""Baseline node initialisers for ablations (same inputs/outputs as MANI's centres).

Each returns ``(centers (N, 3), source_time (N,))``.
"""

from __future__ import annotations

import torch

from .mani import voxel_ids


def farthest_point_sampling(points: torch.Tensor, n: int, seed: int = 0) -> torch.Tensor:
    """Indices ``(min(n, M),)`` of an FPS subset of ``points (M, 3)`` (SC-GS style).

    FPS is inherently sequential: one vectorised distance update per selected node.
    """
    m = points.shape[0]
    n = min(n, m)
    gen = torch.Generator().manual_seed(seed)
    idx = torch.empty(n, dtype=torch.long)
    idx[0] = torch.randint(m, (1,), generator=gen)
    d2 = torch.full((m,), float("inf"))
    for i in range(1, n):
        d2 = torch.minimum(d2, ((points - points[idx[i - 1]]) ** 2).sum(1))
        idx[i] = torch.argmax(d2)
    return idx


def uniform_voxel_centres(points: torch.Tensor, n: int, iters: int = 40) -> torch.Tensor:
    """Mean point of every occupied voxel, voxel size bisected so the count is ≤ ``n``
    and as close to it as the bisection gets. Returns ``(≤ n, 3)``."""
    diag = float((points.max(0).values - points.min(0).values).norm())
    lo, hi = 1e-6 * diag, diag
    best = None
    for _ in range(iters):  # loop over bisection steps
        mid = (lo * hi) ** 0.5
        vox, nv = voxel_ids(points, mid)
        if nv > n:
            lo = mid
        else:
            hi = mid
            best = (vox, nv)
    vox, nv = best if best is not None else voxel_ids(points, diag * 2)
    cnt = torch.bincount(vox, minlength=nv).float().unsqueeze(1)
    return torch.zeros(nv, 3).index_add_(0, vox, points) / cnt


def fill_missing_in_time(x: torch.Tensor) -> torch.Tensor:
    """Forward- then backward-fill NaN rows along dim 1 of ``x (P, F, C)``."""
    p, f, _ = x.shape
    valid = torch.isfinite(x).all(-1)  # [P, F]
    ar = torch.arange(f).expand(p, f)
    last = torch.where(valid, ar, torch.full_like(ar, -1)).cummax(1).values
    nxt = torch.where(valid, ar, torch.full_like(ar, f)).flip(1).cummin(1).values.flip(1)
    src = torch.where(last >= 0, last, nxt).clamp(0, f - 1)
    return x.gather(1, src.unsqueeze(-1).expand_as(x))


def tracklet_clusters(tracks3d: torch.Tensor, n: int, ref_frame: int = 0, iters: int = 30,
                      seed: int = 0) -> torch.Tensor:
    """K-means on concatenated lifted trajectories; centres at ``ref_frame``.

    Parameters
    ----------
    tracks3d : (P, F, 3) with NaN where unobserved (gaps are filled from the nearest
        observation in time; tracks never observed are dropped).

    Returns
    -------
    centers : (≤ n, 3) cluster means at ``ref_frame`` (empty clusters are dropped).
    """
    ok = torch.isfinite(tracks3d).all(-1).any(1)
    x = fill_missing_in_time(tracks3d[ok])
    feats = x.reshape(x.shape[0], -1)
    n = min(n, feats.shape[0])
    gen = torch.Generator().manual_seed(seed)
    cent = feats[torch.randperm(feats.shape[0], generator=gen)[:n]].clone()
    for _ in range(iters):  # Lloyd iterations
        lab = torch.cdist(feats, cent).argmin(1)
        cnt = torch.bincount(lab, minlength=n).float()
        s = torch.zeros_like(cent).index_add_(0, lab, feats)
        cent = torch.where(cnt.unsqueeze(1) > 0, s / cnt.clamp_min(1).unsqueeze(1), cent)
    lab = torch.cdist(feats, cent).argmin(1)
    used = torch.bincount(lab, minlength=n) > 0
    return cent[used].reshape(-1, x.shape[1], 3)[:, ref_frame]
