"""A depth for moving objects that stays with them: per-track constant depth, spread over
the moving pixels of every frame.

The weight-free depth (:func:`engine.priors.estimate_depth`) cannot see moving objects:
its anchors are triangulated static tracks, so a moving object's pixels take the depth of
the static surfaces around and behind it, which changes from frame to frame as the object
crosses the scene (a ball rolling past a wall and then the floor "jumps" in depth). Lifted
with that depth, a 2D track on the object carries made-up motion along the ray, nodes
seated at different frames disagree on where the object is, and Gaussians back-projected
from different frames land at different depths -- the object smears into a ghost.

:func:`track_consistent_depth` gives every moving track one depth -- the median of the
prior along the track -- and paints each moving pixel of each frame with the depth of the
nearest moving track visible there. Depth along a track is then constant, so lifted
tracks move only across the rays (the motion the image shows), and candidates, nodes,
tracks and Gaussians seeded from any frame agree. Used only with the weight-free depth;
a depth model or file sees the objects and is kept as it is.
"""

from __future__ import annotations

import numpy as np


def _along_tracks(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Nearest-pixel values of per-frame images ``img [F, H, W]`` at track positions
    ``xy [P, F, 2]`` (clamped to the image) -> ``[P, F]``."""
    p, f = xy.shape[:2]
    h, w = img.shape[1:]
    col = np.clip(np.floor(np.nan_to_num(xy[..., 0])).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(np.nan_to_num(xy[..., 1])).astype(np.int64), 0, h - 1)
    return img[np.broadcast_to(np.arange(f), (p, f)), row, col]


def moving_tracks(xy: np.ndarray, visible: np.ndarray, dynamic: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Which tracks lie on moving content: the median dynamic prior along the track.

    xy : float [P, F, 2] pixels; visible : bool [P, F]; dynamic : float [F, H, W] in [0, 1].
    Returns bool [P] (False for tracks never visible).
    """
    val = np.where(visible, _along_tracks(dynamic, xy), np.nan)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(visible.any(1, keepdims=True), val, 0.0), axis=1)
    return np.nan_to_num(med, nan=0.0) >= threshold


def track_consistent_depth(depth: np.ndarray, dynamic: np.ndarray, xy: np.ndarray, visible: np.ndarray,
                           threshold: float = 0.5, max_px: float | None = None) -> tuple[np.ndarray, dict]:
    """Depth with one value per moving track, spread to the moving pixels of each frame.

    Parameters
    ----------
    depth : float [F, H, W] (0 = unknown); dynamic : float [F, H, W] dynamic prior;
    xy : float [P, F, 2] track pixels; visible : bool [P, F]; frames in time order.
    threshold : a pixel / track is moving where the prior is at least this.
    max_px : moving pixels farther than this from every moving track visible in their
        frame keep their depth (default: 1/8 of the image diagonal).

    Returns
    -------
    depth' float32 [F, H, W] and stats ``{"moving_tracks", "painted_px", "frames"}``.
    """
    from scipy.spatial import cKDTree

    f, h, w = depth.shape
    max_px = float(max_px if max_px is not None else 0.125 * np.hypot(h, w))
    out = depth.astype(np.float32, copy=True)
    moving = moving_tracks(xy, visible, dynamic, threshold)
    stats = {"moving_tracks": int(moving.sum()), "painted_px": 0, "frames": 0}
    if not moving.any():
        return out, stats
    mxy, mvis = xy[moving], visible[moving]
    z = _along_tracks(depth, mxy)
    z = np.where(mvis & (z > 0) & np.isfinite(z), z, np.nan)
    with np.errstate(all="ignore"):
        # log-median: the typical depth of what the track saw, robust to the frames where
        # the prior switched surface behind the object
        z_track = np.exp(np.nanmedian(np.log(z), axis=1))
    has = np.isfinite(z_track)
    for k in range(f):  # one KD-tree per frame; every pixel query of the frame is vectorised
        on = mvis[:, k] & has
        ys, xs = np.nonzero(dynamic[k] >= threshold)
        if not on.any() or not len(ys):
            continue
        tree = cKDTree(mxy[on, k])
        dist, j = tree.query(np.stack([xs + 0.5, ys + 0.5], 1), k=1)
        near = dist <= max_px
        out[k, ys[near], xs[near]] = z_track[on][j[near]].astype(np.float32)
        stats["painted_px"] += int(near.sum())
        stats["frames"] += 1
    return out, stats
