"""Patch-to-node candidates: every patch centre of every keyframe lifted to 3D."""

from __future__ import annotations

from dataclasses import dataclass, fields

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
                     keyframes: torch.Tensor, dynamic_density: int = 1, dynamic_threshold: float = 0.5,
                     dynamic_max_share: float = 0.25) -> Candidates:
    """Back-project every patch centre of the keyframes with its aligned depth.

    Parameters
    ----------
    depth : (F, H, W) camera-z depth (≤ 0 or non-finite = invalid).
    K : (F, 3, 3); w2c : (F, 4, 4); times : (F,) engine time.
    tokens : (F, Gh, Gw, D); patch_centers : (Gh, Gw, 2) pixel coords in the depth image.
    fg : (F, H, W) foreground / dynamic prior in [0, 1].
    keyframes : (Fk,) long frame indices.
    dynamic_density : > 1 adds candidates on moving pixels (``fg >= dynamic_threshold``) on a
        grid this many times finer than the patch grid (:func:`_moving_candidates`), at most
        ``dynamic_max_share`` times as many as the patch-grid candidates.

    Returns
    -------
    Candidates with ``M ≤ Fk·Gh·Gw`` rows from the patch grid (patches with invalid depth
    are dropped), then the moving-pixel ones.
    """
    f = keyframes.long()
    gh, gw, d = tokens.shape[1:]
    uv = patch_centers.reshape(1, gh * gw, 2).to(depth.dtype).expand(f.shape[0], -1, -1)  # [Fk, P, 2]
    cand = _lift(depth, K, w2c, times, fg, f, uv, tokens[f].reshape(f.shape[0], gh * gw, d))
    if dynamic_density > 1:
        extra = _moving_candidates(depth, K, w2c, times, tokens, patch_centers, fg, f, dynamic_density,
                                   dynamic_threshold)
        cap = int(dynamic_max_share * cand.positions.shape[0])
        if extra.positions.shape[0] > cap:
            # a prior that calls a third of the image moving (real footage: a breathing torso,
            # shadows) would flood MANI with moving candidates and take the nodes from the
            # static scene: cups.mp4 -1.4 dB uncapped. Evenly spaced, so it stays deterministic.
            keep = torch.linspace(0, extra.positions.shape[0] - 1, max(cap, 0)).round().long()
            extra = Candidates(*(getattr(extra, k.name)[keep] for k in fields(Candidates)))
        cand = Candidates(*(torch.cat([getattr(cand, k.name), getattr(extra, k.name)]) for k in fields(Candidates)))
    return cand


def _lift(depth, K, w2c, times, fg, f, uv, tok, min_fg: float | None = None) -> Candidates:
    """Back-project pixels ``uv [Fk, P, 2]`` of keyframes ``f [Fk]`` carrying tokens
    ``tok [Fk, P, D]``; pixels with invalid depth (or a dynamic prior below ``min_fg``)
    are dropped. Other shapes as :func:`build_candidates`."""
    z = torch.stack([sample_nearest(depth[i], uv[j]) for j, i in enumerate(f.tolist())])  # loop over keyframes
    m = torch.stack([sample_nearest(fg[i], uv[j]) for j, i in enumerate(f.tolist())])
    x = unproject(K[f].unsqueeze(1).to(depth.dtype), w2c[f].unsqueeze(1).to(depth.dtype), uv, z)  # [Fk, P, 3]
    valid = torch.isfinite(z) & (z > 0) & torch.isfinite(x).all(-1)
    if min_fg is not None:
        valid &= torch.nan_to_num(m, nan=0.0) >= min_fg
    frame = f.unsqueeze(1).expand(-1, uv.shape[1])
    return Candidates(
        positions=x[valid].float(),
        tokens=tok[valid].float(),
        fg=torch.nan_to_num(m[valid], nan=0.0).clamp(0, 1).float(),
        frame=frame[valid],
        time=times.to(torch.float32)[frame[valid]],
        pixel=uv[valid].float(),
    )


def _moving_candidates(depth, K, w2c, times, tokens, patch_centers, fg, keyframes, density: int,
                       threshold: float) -> Candidates:
    """Extra candidates on moving pixels: a grid ``density`` times finer than the patch grid
    (the patch centres themselves excluded), each carrying its patch's token.

    A moving object a few patches wide gets a handful of candidates per keyframe from the
    patch grid alone, too few for MANI to keep "many nodes where it moves": a two-link limb
    then had two or three nodes, which cannot bend it. Shapes as :func:`build_candidates`.
    """
    gh, gw, d = tokens.shape[1:]
    pc = patch_centers.to(depth.dtype)
    step_x = (pc[0, -1, 0] - pc[0, 0, 0]) / max(gw - 1, 1) if gw > 1 else torch.tensor(8.0)
    step_y = (pc[-1, 0, 1] - pc[0, 0, 1]) / max(gh - 1, 1) if gh > 1 else step_x
    offs = (torch.arange(density, dtype=depth.dtype) + 0.5) / density - 0.5  # sub-patch offsets in [-0.5, 0.5)
    oy, ox = torch.meshgrid(offs * step_y, offs * step_x, indexing="ij")
    sub = torch.stack([ox, oy], -1).reshape(1, 1, -1, 2)  # [1, 1, S, 2]
    centre = (ox.abs() < 1e-6) & (oy.abs() < 1e-6)
    sub = sub[:, :, ~centre.reshape(-1)]
    uv = (pc.reshape(gh * gw, 1, 2) + sub[0]).reshape(1, -1, 2)  # [1, P*S, 2]
    patch = torch.arange(gh * gw).repeat_interleave(sub.shape[2])  # token of each sub-point
    f = keyframes.long()
    uv = uv.expand(f.shape[0], -1, -1)
    return _lift(depth, K, w2c, times, fg, f, uv, tokens[f].reshape(f.shape[0], gh * gw, d)[:, patch], threshold)
