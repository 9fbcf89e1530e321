"""Patch-to-node candidates: every patch centre of every keyframe lifted to 3D."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..geometry.camera import unproject


@dataclass
class Candidates:
    """Candidate nodes (one per valid patch of each keyframe).

    positions : (M, 3) world points; tokens : (M, D); fg : (M,) foreground prior in [0, 1];
    frame : (M,) long source frame index; time : (M,) engine time of that frame;
    pixel : (M, 2) patch centre in continuous pixel coordinates.
    """

    positions: torch.Tensor
    tokens: torch.Tensor
    fg: torch.Tensor
    frame: torch.Tensor
    time: torch.Tensor
    pixel: torch.Tensor


def choose_keyframes(num_frames: int, num_keyframes: int) -> torch.Tensor:
    """Evenly spaced frame indices including the first and last frame (``(min(F, n),)`` long)."""
    n = max(1, min(num_frames, num_keyframes))
    return torch.unique(torch.linspace(0, num_frames - 1, n).round().long())


def sample_nearest(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Nearest-pixel lookup of ``img (H, W)`` at continuous coords ``uv (..., 2)``.

    Nearest (not bilinear) so depth is never averaged across an occlusion edge.
    Out-of-image coordinates return NaN.
    """
    h, w = img.shape
    col = torch.floor(uv[..., 0]).long()
    row = torch.floor(uv[..., 1]).long()
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    vals = img[row.clamp(0, h - 1), col.clamp(0, w - 1)]
    return torch.where(inside, vals, torch.full_like(vals, float("nan")))


def build_candidates(depth: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, times: torch.Tensor,
                     tokens: torch.Tensor, patch_centers: torch.Tensor, fg: torch.Tensor,
                     keyframes: torch.Tensor) -> Candidates:
    """Back-project every patch centre of the keyframes with its aligned depth.

    Parameters
    ----------
    depth : (F, H, W) camera-z depth (≤ 0 or non-finite = invalid).
    K : (F, 3, 3); w2c : (F, 4, 4); times : (F,) engine time.
    tokens : (F, Gh, Gw, D); patch_centers : (Gh, Gw, 2) pixel coords in the depth image.
    fg : (F, H, W) foreground / dynamic prior in [0, 1].
    keyframes : (Fk,) long frame indices.

    Returns
    -------
    Candidates with ``M ≤ Fk·Gh·Gw`` rows (patches with invalid depth are dropped).
    """
    f = keyframes.long()
    gh, gw, d = tokens.shape[1:]
    uv = patch_centers.reshape(1, gh * gw, 2).to(depth.dtype).expand(f.shape[0], -1, -1)  # [Fk, P, 2]
    z = torch.stack([sample_nearest(depth[i], uv[j]) for j, i in enumerate(f.tolist())])  # loop over keyframes
    m = torch.stack([sample_nearest(fg[i], uv[j]) for j, i in enumerate(f.tolist())])
    x = unproject(K[f].unsqueeze(1).to(depth.dtype), w2c[f].unsqueeze(1).to(depth.dtype), uv, z)  # [Fk, P, 3]
    valid = torch.isfinite(z) & (z > 0) & torch.isfinite(x).all(-1)
    frame = f.unsqueeze(1).expand(-1, gh * gw)
    return Candidates(
        positions=x[valid].float(),
        tokens=tokens[f].reshape(f.shape[0], gh * gw, d)[valid].float(),
        fg=torch.nan_to_num(m[valid], nan=0.0).clamp(0, 1).float(),
        frame=frame[valid],
        time=times.to(torch.float32)[frame[valid]],
        pixel=uv[valid].float(),
    )
