"""Objects at rest that move at another time: dynamic in every frame (cameras that do not translate).

Why: the motion prior (:mod:`engine.priors.motion`) calls a pixel dynamic in the frames where
something *moves* there. A cup that rests for most of a clip and is lifted, shuffled and set
down elsewhere is still in most frames, so the static / dynamic split
(:mod:`engine.train.split`) gives it to the static Gaussians, which are undeformed and
always visible: the cup stays rendered where it rested after the hand has taken it away, and
where it rests only briefly it is a faint copy (``cups.mp4``, whole clip: ghost cups in the
contact sheets, docs/benchmarks.md). No static model can be right there: the pixel shows
two still states at different times.

For a camera that does not translate the pixels line up over time (after the rotation's
homography), so the still states can be compared directly: each frame against the clip's
per-pixel median (its still plate). A pixel whose colour differs from the plate by more than
``threshold`` while the motion prior calls it still, in at least ``min_frames`` frames, holds
an object at rest at some time and not at another (or the background it uncovered). Those
pixels are made dynamic in *every* frame, so the object is seeded as moving content at every
time (with lifespans: visible around each frame it was seen in) and never as a static copy.

Steps (at most ``max_width`` px; frames warped to the middle frame by ``K R_ref R_f^T K^-1``
when the camera turns): per-frame, per-channel gain against the plate on the still pixels
(exposure drift is not an object), colour distance to the plate, minus the pixels the motion
prior calls moving, 3x3 opening per frame (single-pixel noise), count over frames, 3x3
closing, then back to each frame's view and resolution and max-ed with the motion prior.
A result covering more than ``max_share`` of the view is not an object but a change of the
whole picture (light, a cut): the prior is then left as it was.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..geometry.camera import camera_translates


@dataclass
class RestingConfig:
    """Settings of :func:`resting_objects` (colour distance on RGB in [0, 1])."""

    threshold: float = 0.12
    min_frames: int = 3
    min_frame_share: float = 0.02  # ... and at least this share of the frames
    max_width: int = 320
    max_share: float = 0.6
    dynamic_threshold: float = 0.5


def _to_reference(K: np.ndarray, w2c: np.ndarray, ref: int) -> np.ndarray | None:
    """Homographies ``[F, 3, 3]`` from each frame's pixels to frame ``ref``'s for a camera that
    turns about a fixed centre (``K_ref R_ref R_f^T K_f^-1``), None when no frame turns."""
    R = w2c[:, :3, :3]
    rel = R[ref][None] @ np.transpose(R, (0, 2, 1))
    if np.abs(rel - np.eye(3)[None]).max() < 1e-9 and np.abs(K - K[ref][None]).max() < 1e-9:
        return None
    return K[ref][None] @ rel @ np.linalg.inv(K)


def _median_plate(frames: np.ndarray, valid: np.ndarray, rows: int = 16) -> np.ndarray:
    """Per-pixel median ``[h, w, 3]`` of ``frames [F, h, w, 3]`` over the frames where
    ``valid [F, h, w]``; row blocks keep the working copy small."""
    f, h, w, _ = frames.shape
    out = np.zeros((h, w, 3), np.float32)
    for y0 in range(0, h, rows):  # blocks of rows; every pixel and frame of a block at once
        blk = frames[:, y0:y0 + rows].astype(np.float32)
        blk[~valid[:, y0:y0 + rows]] = np.nan
        with np.errstate(all="ignore"):
            med = np.nanmedian(blk, axis=0)
        out[y0:y0 + rows] = np.nan_to_num(med, nan=0.0)
    return out


def resting_objects(frames: np.ndarray, dynamic: np.ndarray, K: np.ndarray, w2c: np.ndarray, extent: float,
                    config: RestingConfig | None = None) -> tuple[np.ndarray | None, dict]:
    """The dynamic prior with objects that rest at some times and move at others made dynamic
    in every frame (module docstring).

    Parameters
    ----------
    frames : uint8 [F, H, W, 3] in time order; dynamic : float [F, H, W] in [0, 1], the
    motion prior; K : [F, 3, 3]; w2c : [F, 4, 4]; extent : the scene's size (what "does not
    translate" is measured against, :func:`engine.geometry.camera.camera_translates`).

    Returns
    -------
    (dynamic [F, H, W] float32 or None, stats): None when the step does not apply (a camera
    that translates, fewer than 3 frames, or a change of the whole view); stats ``share`` (of
    the reference view made dynamic), ``frames_needed``, ``applied`` and ``reason``.
    """
    import cv2

    cfg = config or RestingConfig()
    F, H, W = dynamic.shape
    stats = {"applied": False, "share": 0.0, "frames_needed": 0, "reason": ""}
    if F < 3:
        stats["reason"] = "fewer than 3 frames"
        return None, stats
    if camera_translates(torch.as_tensor(np.asarray(w2c, np.float64)), extent):
        stats["reason"] = "the camera translates"
        return None, stats
    s = min(1.0, cfg.max_width / W)
    w, h = max(1, round(W * s)), max(1, round(H * s))
    Ks = np.asarray(K, np.float64).copy()
    Ks[:, :2] *= np.array([w / W, h / H])[None, :, None]
    small = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in frames]).astype(np.float32) / 255
    dyn = np.stack([cv2.resize(d.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) for d in dynamic])
    ref = F // 2
    Hs = _to_reference(Ks, np.asarray(w2c, np.float64), ref)
    valid = np.ones((F, h, w), bool)
    if Hs is not None:  # a turning camera: compare in the reference frame's pixels
        ones = np.ones((h, w), np.float32)
        warp = lambda a, M, flags=cv2.INTER_LINEAR: cv2.warpPerspective(a, M, (w, h), flags=flags)  # noqa: E731
        small = np.stack([warp(small[f], Hs[f]) for f in range(F)])
        dyn = np.stack([warp(dyn[f], Hs[f]) for f in range(F)])
        valid = np.stack([warp(ones, Hs[f], cv2.INTER_NEAREST) > 0.5 for f in range(F)])
    still = (dyn < cfg.dynamic_threshold) & valid
    # the plate: each pixel's median over the frames where it is still (all its frames if never)
    plate = _median_plate(small, still | (~np.any(still, 0, keepdims=True) & valid))
    # exposure drift: one gain per frame and channel, from the still pixels
    num = np.where(still[..., None], plate[None], 0).sum((1, 2))
    den = np.where(still[..., None], small, 0).sum((1, 2))
    gain = np.where(den > 1e-6, num / np.maximum(den, 1e-6), 1.0).astype(np.float32)  # [F, 3]
    dist = np.linalg.norm(small * gain[:, None, None] - plate[None], axis=-1)  # [F, h, w]
    changed = (dist > cfg.threshold) & still
    k3 = np.ones((3, 3), np.uint8)
    changed = np.stack([cv2.morphologyEx(c.astype(np.uint8), cv2.MORPH_OPEN, k3) for c in changed]).astype(bool)
    need = max(cfg.min_frames, math.ceil(cfg.min_frame_share * F))
    resting = cv2.morphologyEx((changed.sum(0) >= need).astype(np.uint8), cv2.MORPH_CLOSE, k3).astype(np.float32)
    share = float(resting[valid.all(0)].mean()) if valid.all(0).any() else float(resting.mean())
    stats.update(share=share, frames_needed=need)
    if share > cfg.max_share:
        stats["reason"] = f"{share:.0%} of the view changes: a change of the whole picture, not an object"
        return None, stats
    out = np.asarray(dynamic, np.float32).copy()
    for f in range(F):  # back to each frame's view and resolution; pixels vectorised
        r = resting if Hs is None else cv2.warpPerspective(resting, np.linalg.inv(Hs[f]), (w, h),
                                                            flags=cv2.INTER_LINEAR)
        out[f] = np.maximum(out[f], cv2.resize(r, (W, H), interpolation=cv2.INTER_LINEAR))
    stats["applied"] = True
    return np.clip(out, 0.0, 1.0), stats
