"""A compact blob's turn: the rotation of a sphere through its outline, frame by frame, from
the flow's tracks inside it.

Blob tracks (:mod:`engine.priors.blob_tracks`) move with the blob's centroid; a rolling ball's
surface also turns about its centre (~9 degrees a frame on the generated large-motion scenes), so
a point that keeps its offset from the centroid is off by up to the ball's radius within a few
frames: the generated ball's blob tracks missed its points by 10-11 px median. The flow's own
tracks on the ball live a few frames, but between two frames they show the turn.

The blob is taken for a sphere of the radius of a disc of its area (one physical size: that
radius times the blob's depth is held over the path). A pixel inside it at offset ``o`` (in
radii) from the centroid is the front point ``(o_x, o_y, -sqrt(1 - |o|^2))`` of the unit sphere
(camera axes, orthographic across the blob: its radius is a few per cent of its depth). For
each pair of consecutive frames the flow's tracks inside the blob at both give such points at
both, and the rotation about the centre that carries the first onto the second (Kabsch,
:func:`engine.geometry.poses.kabsch_rotation`, refitted without the tracks it does not
explain) is the step's turn. Steps without enough tracks take their neighbours' (interpolated),
and a running median over 5 steps steadies it; composed, they turn every seeded point, which
is seen while it faces the camera.

A blob that does not turn still gets a fit, of the flow's noise, and composed over a path
that noise walks the points off; one that turns slowly is not a sphere's turn either. So a path
turns only where the turn is most of what its tracks do: the median over its steps of the
residual without a turn over the residual with it is at least ``min_gain`` (3). The generated
rolling ball: 4.0 / 4.3 (~9 degrees a step). A blob sliding without a turn, under 0.3 px of
flow noise: 1.0 (its fits turn it half a degree a step). The generated quality scene's cube,
turning 2.2 degrees a frame: 2.0, fitted at 3.2 degrees a step (a cube's face is no sphere);
turned, its scene's node trajectories came out worse (ratio 0.94 -> 0.98; docs/benchmarks.md,
*A rolling ball's turn*).
"""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.poses import kabsch_rotation
from ..geometry.quaternion import quat_from_axis_angle, quat_from_matrix, quat_to_matrix, quat_to_rotation_vector


def sphere_points(offset: np.ndarray) -> np.ndarray:
    """Front points of the unit sphere under image offsets ``offset [..., 2]`` (in radii from
    the centre; clipped onto the outline) -> ``[..., 3]`` in camera axes (z away from the camera:
    the front is z < 0)."""
    offset = offset / np.maximum(np.linalg.norm(offset, axis=-1, keepdims=True), 1.0)
    return np.concatenate([offset, -np.sqrt(np.clip(1.0 - (offset ** 2).sum(-1), 0.0, 1.0))[..., None]], -1)


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Axis times angle of rotations ``R [..., 3, 3]`` -> ``[..., 3]`` (engine/geometry/quaternion.py)."""
    q = quat_from_matrix(torch.as_tensor(np.asarray(R), dtype=torch.float64))
    return quat_to_rotation_vector(q).numpy()


def _rotmat(v: np.ndarray) -> np.ndarray:
    """Rotations ``[..., 3, 3]`` from axis-times-angle ``v [..., 3]`` (engine/geometry/quaternion.py)."""
    v = torch.as_tensor(np.asarray(v), dtype=torch.float64)
    return quat_to_matrix(quat_from_axis_angle(v, v.norm(dim=-1))).numpy()


def step_turns(labels: list, label: np.ndarray, centre: np.ndarray, radius: np.ndarray, on: np.ndarray,
               flow_xy: np.ndarray, flow_vis: np.ndarray, min_tracks: int = 5, max_offset: float = 0.9,
               rounds: int = 3, min_residual: float = 0.15) -> np.ndarray:
    """The blob's rotation from each frame to the next, from the flow's tracks inside it.

    Parameters
    ----------
    labels : F label images [H, W] (the motion mask's blobs); label : int [F] the blob's label
        per frame; centre : float [F, 2] its centroid (px); radius : float [F] its radius (px);
        on : bool [F] frames where the blob is seen.
    flow_xy, flow_vis : float [P, F, 2], bool [P, F]: the flow's tracks.
    min_tracks : fewest tracks inside the blob at both frames for a fit; max_offset : tracks
        farther than this (in radii) from the centre are left out (near the outline the front
        point is ill-defined and the flow mixes in the background).
    rounds, min_residual : refits without the tracks off by more than max(min_residual, 2.5 x
        the median residual) on the unit sphere.

    Returns
    -------
    turns : float [F - 1, 3]: axis times angle of each step's turn (camera axes), NaN where no fit.
    gain : float [F - 1]: the tracks' median residual without the turn over that with it (NaN
        where no fit; :func:`turn_path` turns a path only where it is high enough).
    """
    f = len(on)
    out = np.full((f - 1, 3), np.nan)
    gain = np.full(f - 1, np.nan)
    for k in np.nonzero(on[:-1] & on[1:])[0]:  # consecutive frames of the path
        both = flow_vis[:, k] & flow_vis[:, k + 1]
        a, b = flow_xy[both, k].astype(np.float64), flow_xy[both, k + 1].astype(np.float64)
        ok = np.ones(len(a), bool)
        for kk, xy in ((k, a), (k + 1, b)):
            h, w = labels[kk].shape
            ok &= labels[kk][np.clip(xy[:, 1].astype(np.int64), 0, h - 1),
                             np.clip(xy[:, 0].astype(np.int64), 0, w - 1)] == label[kk]
        oa, ob = (a - centre[k]) / radius[k], (b - centre[k + 1]) / radius[k + 1]
        ok &= ((oa ** 2).sum(1) < max_offset ** 2) & ((ob ** 2).sum(1) < max_offset ** 2)
        if ok.sum() < min_tracks:
            continue
        sa, sb = sphere_points(oa[ok]), sphere_points(ob[ok])
        keep = np.ones(len(sa), bool)
        for _ in range(rounds):  # robust refits (a few)
            R = kabsch_rotation(sa[keep], sb[keep])
            res = np.linalg.norm(sa @ R.T - sb, axis=1)
            keep = res <= max(min_residual, 2.5 * float(np.median(res)))
            if keep.sum() < min_tracks:
                break
        if keep.sum() >= min_tracks:
            R = kabsch_rotation(sa[keep], sb[keep])
            out[k] = _rotvec(R)
            still = float(np.median(np.linalg.norm(sa[keep] - sb[keep], axis=1)))
            gain[k] = still / max(float(np.median(np.linalg.norm(sa[keep] @ R.T - sb[keep], axis=1))), 1e-6)
    return out, gain


def turn_path(steps: np.ndarray, first: int, last: int, gain: np.ndarray | None = None, min_gain: float = 3.0,
              window: int = 5) -> np.ndarray | None:
    """Each frame's rotation from frame ``first`` (``R [F, 3, 3]``, the identity outside
    ``first..last``) by composing the steps ``steps [F - 1, 3]`` (:func:`step_turns`) between
    them: steps without a fit interpolated from their neighbours', then a running median over
    ``window`` steps. None when no step between them has a fit (the turn is unknown), or when
    the median ``gain`` of their fits is under ``min_gain`` (the fits are the tracks' noise:
    module docstring)."""
    f = len(steps) + 1
    idx = np.arange(first, last)
    have = idx[np.isfinite(steps[idx, 0])]
    if not len(have) or (gain is not None and not float(np.median(gain[have])) >= min_gain):
        return None
    filled = np.stack([np.interp(idx, have, steps[have, d]) for d in range(3)], 1)  # [S, 3]
    half = window // 2
    pad = np.pad(filled, ((half, half), (0, 0)), mode="edge")
    smooth = np.median(np.lib.stride_tricks.sliding_window_view(pad, window, axis=0), axis=-1)  # [S, 3]
    step_R = _rotmat(smooth)
    R = np.tile(np.eye(3), (f, 1, 1))
    for i, k in enumerate(idx):  # composition is sequential (a few dozen steps)
        R[k + 1] = step_R[i] @ R[k]
    R[last + 1:] = np.eye(3)
    return R
