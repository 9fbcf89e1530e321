"""The still-plate baseline: how well one photograph of the background scores.

A dynamic reconstruction that lost every moving object still scores like the clip's median
frame (the background with the movers averaged away), so every quality figure needs this
baseline beside it. The plate is the per-pixel median of the training frames; its PSNR
against each training frame (whole image, and inside the dynamic mask when there is one)
is what a model that reproduces no motion at all would get.

``still_plate_scores`` works on arrays (the bench); ``engine train``'s print scores a plate of
the training frames on the withheld ones with ``still_plate`` + ``plate_psnr``;
``bundle_split_frames`` loads a bundle's split frames and masks from its clip.
"""

from __future__ import annotations

import numpy as np


def still_plate(frames: np.ndarray) -> np.ndarray:
    """Per-pixel median of ``frames`` (uint8 ``[F, H, W, 3]``) → uint8 ``[H, W, 3]``."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[0] < 1:
        raise ValueError(f"frames must be [F, H, W, C] with F >= 1, got shape {frames.shape}")
    return np.median(frames, axis=0).round().astype(np.uint8)


def plate_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of uint8 images ``[H, W, 3]`` on [0, 1] (``engine.train.losses.psnr``'s
    definition: MSE over every channel of the masked pixels, clamped at 1e-12)."""
    err = ((a.astype(np.float64) - b.astype(np.float64)) / 255.0) ** 2
    mse = err[mask].mean() if mask is not None else err.mean()
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def still_plate_scores(frames: np.ndarray, masks: np.ndarray | None = None, min_pixels: int = 16) -> dict:
    """Mean PSNR of the median frame against every frame, whole image and masked.

    Parameters
    ----------
    frames : uint8 ``[F, H, W, 3]`` training frames (the plate is their median).
    masks : optional bool ``[F, H, W]`` dynamic masks; frames whose mask has at most
        ``min_pixels`` pixels are left out of the masked mean (as ``engine eval`` does).

    Returns
    -------
    dict with ``plate_psnr`` (mean over frames), ``plate_masked_psnr`` (mean over frames
    with a mask, None without masks) and ``frames``.
    """
    frames = np.asarray(frames)
    plate = still_plate(frames)
    whole = [plate_psnr(plate, f) for f in frames]
    masked = []
    if masks is not None:
        masks = np.asarray(masks, bool)
        if masks.shape != frames.shape[:3]:
            raise ValueError(f"masks {masks.shape} do not match frames {frames.shape[:3]}")
        masked = [plate_psnr(plate, f, m) for f, m in zip(frames, masks) if m.sum() > min_pixels]
    return {"plate_psnr": float(np.mean(whole)), "plate_masked_psnr": float(np.mean(masked)) if masked else None,
            "frames": int(len(frames))}


def bundle_split_frames(bundle_dir, split: str = "train", clip_path=None):
    """The clip frames (and dynamic masks) a bundle's ``split`` cameras saw, at their size.

    Returns ``(frames uint8 [F, H, W, 3], masks bool [F, H, W] or None)``; masks are None
    unless every frame has one (dataset masks or a generated scene's ground truth).
    """
    import cv2

    from ..bundle import load_bundle
    from ..commands.eval import _camera_frame, _mask_for, _open_clip_for

    bundle = load_bundle(bundle_dir)
    cams = [c for c in bundle.scene["cameras"] if c.get("split", "train") == split]
    clip, path = _open_clip_for(bundle, clip_path)
    start = int(clip.meta.get("frame_start", 1)) if isinstance(clip.meta, dict) else 1
    frames, masks = [], []
    for c in cams:
        i, img = _camera_frame(clip, c, start, path)
        frames.append(img)
        m = _mask_for(clip, i)
        masks.append(None if m is None else cv2.resize(m.astype(np.uint8), (img.shape[1], img.shape[0]),
                                                       interpolation=cv2.INTER_NEAREST) > 0)
    have = all(m is not None for m in masks) and bool(masks)
    return np.stack(frames), (np.stack(masks) if have else None)
