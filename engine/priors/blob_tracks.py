"""Blob tracks: long 2D tracks on a compact moving object, from its blob's path.

The tracker's flow loses a fast object within a few frames (a rolling ball's DIS tracks live
~17 of 60 frames on the generated large-motion scenes), so the node paths fitted to them
follow it only near the frames the tracks came from; the ball holds half of the moving parts'
zero-motion error there (docs/benchmarks.md, *Where large seed 1's node ratio comes from*). Its
blob in the motion mask, though, is there in every frame it does not touch something else.

A *compact* blob (convex: its area over its convex hull's, the solidity, at least
``min_solidity`` in most frames; and round-ish: an elongated one, a rod or a limb, turns in
the image as it moves) that keeps its size, and whose centroid steps as the flow's tracks
inside it do (a motion mask spread over a person and a table moves its centroid as it grows
and shrinks, while the pixels under it barely move), is followed from frame to frame by its
centroid: the blob of the next frame nearest the centroid's constant-velocity prediction,
within ``max_jump_px`` and of a similar size, continues it (a frame where it merges with
another blob, or none is near, is bridged for up to ``max_gap`` frames: the tracks are not
seen there, but one track spans both sides). Every pixel of the
blob at a seed frame becomes a track that keeps its offset from the centroid, scaled by the
blob's depth (an object nearer the camera looks larger). A rolling ball's points also turn
about its centre, which the flow's own tracks show between two frames: with them the blob turns
as a sphere through its outline (:mod:`engine.priors.blob_turn`), its tracks are points of that
sphere, seen while they face the camera (the generated ball's tracks: 10-11 px median error
moved by the centroid alone, 3-5 px turned). A body that is not compact (a person, an arm, a
cloth) changes its outline as its parts move, so its centroid is not any point's path: it gets
none.

The tracks carry their own camera depth: the median of the depth map over the blob, frame by
frame, smoothed over the path (:func:`_smooth_log`; the per-track depth gives a track one depth
for its whole life). Those of a blob whose turn is unknown (no flow, no step with enough of its
tracks, or fits no better than the flow's noise) are flagged ``translation_only``: the node
rotations are fitted without them.
"""

from __future__ import annotations

import numpy as np

from .blob_turn import sphere_points, step_turns, turn_path
from .tracks import Tracks, concat_tracks, tracks_from_paths


def _blobs(mask: np.ndarray, min_px: int):
    """``(labels [H, W], blobs)``: 8-connected components of ``mask`` with ``min_px`` pixels or
    more, each ``(label, area, centroid [2] px, solidity, roundness)``."""
    import cv2
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return labels, []
    idx = np.arange(1, n + 1)
    area = ndimage.sum_labels(np.ones_like(labels), labels, idx)
    cy, cx = np.asarray(ndimage.center_of_mass(np.ones_like(labels), labels, idx)).reshape(-1, 2).T
    out = []
    for i in np.nonzero(area >= min_px)[0]:  # blobs (a few per frame)
        ys, xs = np.nonzero(labels == idx[i])
        hull = cv2.convexHull(np.stack([xs, ys], 1).astype(np.int32))
        solidity = float(area[i]) / max(float(cv2.contourArea(hull)) + 0.5 * len(hull), 1.0)
        # roundness: minor over major axis of the blob's second moments (1 = a disc, 0.5 = a 2:1 box)
        ev = np.linalg.eigvalsh(np.cov(np.stack([xs, ys]).astype(np.float64)) + 1e-9 * np.eye(2))
        roundness = float(np.sqrt(max(ev[0], 0.0) / max(ev[1], 1e-12)))
        out.append((int(idx[i]), float(area[i]), np.array([cx[i] + 0.5, cy[i] + 0.5]), min(solidity, 1.0), roundness))
    return labels, out


def _chains(blobs, max_jump_px: float, size_tol: float, max_gap: int):
    """Link each frame's blobs into paths: ``[[(frame, blob index), ...], ...]``.

    Frame by frame, every path seen within the last ``max_gap + 1`` frames predicts its
    centroid (constant velocity over its last two blobs); pairs of path and blob within
    ``max_jump_px`` per elapsed frame and with an area within ``size_tol`` x the path's last
    three blobs' median are taken nearest first, each path and blob once; a blob left over
    starts a path.
    """
    paths: list[list[tuple[int, int]]] = []
    for k, frame in enumerate(blobs):  # frames, in time order
        pairs = []
        for p, path in enumerate(paths):  # paths alive at k (a few)
            last_f, last_i = path[-1]
            gap = k - last_f
            if gap > max_gap + 1:
                continue
            c = blobs[last_f][last_i][2]
            vel = np.zeros(2)
            if len(path) > 1:
                pf, pi = path[-2]
                vel = (c - blobs[pf][pi][2]) / (last_f - pf)
            # the recent size: an object coming nearer grows gradually, a merge at once
            area = float(np.median([blobs[a][b][1] for a, b in path[-3:]]))
            for n, b in enumerate(frame):
                d = float(np.linalg.norm(b[2] - (c + gap * vel)))
                if d <= max_jump_px * gap and 1.0 / size_tol <= b[1] / area <= size_tol:
                    pairs.append((d, p, n))
        used_p, used_n = set(), set()
        for d, p, n in sorted(pairs):
            if p in used_p or n in used_n:
                continue
            used_p.add(p)
            used_n.add(n)
            paths[p].append((k, n))
        paths += [[(k, n)] for n in range(len(frame)) if n not in used_n]
    return paths


def _smooth_log(t: np.ndarray, z: np.ndarray, degree: int = 3, clip: float = 2.5, rounds: int = 3) -> np.ndarray:
    """``z [T]`` (> 0) at frames ``t [T]`` smoothed: a cubic in log depth, refitted without the
    samples over ``clip`` standard deviations off it. The blob's median depth jitters by ~4 %
    from frame to frame on the generated ball (its true depth by 0.3-1 %), and each jitter
    moves the lifted tracks along their rays."""
    lz = np.log(z)
    deg = min(degree, len(t) - 1)
    keep = np.ones(len(t), bool)
    for _ in range(rounds):  # robust refits (a few)
        coef = np.polyfit(t[keep], lz[keep], deg)
        res = lz - np.polyval(coef, t)
        keep = np.abs(res) <= clip * max(float(np.std(res[keep])), 1e-3)
    return np.exp(np.polyval(coef, t))


def _moves_with_its_pixels(labels, blob, pf, flow_xy, flow_vis, min_tracks: int = 3, tol: float = 0.5,
                           tol_px: float = 1.5) -> float:
    """Share of a path's consecutive frames where the blob's centroid steps as the flow's tracks
    inside it do: ``|median(track step) − centroid step| <= tol |centroid step| + tol_px``
    (frames with fewer than ``min_tracks`` such tracks do not count; NaN when none counts).

    A rigid object's pixels move with it; a motion mask that grows, shrinks or slides over a
    person and a table moves its centroid while the pixels under it barely do."""
    agree = []
    for (k0, b0), (k1, b1) in zip(zip(pf[:-1], blob[:-1]), zip(pf[1:], blob[1:])):  # path steps
        if k1 != k0 + 1:
            continue
        on = flow_vis[:, k0] & flow_vis[:, k1]
        xy0 = flow_xy[on, k0]
        col = np.clip(xy0[:, 0].astype(np.int64), 0, labels[k0].shape[1] - 1)
        row = np.clip(xy0[:, 1].astype(np.int64), 0, labels[k0].shape[0] - 1)
        inside = labels[k0][row, col] == b0[0]
        if inside.sum() < min_tracks:
            continue
        step = np.median(flow_xy[on, k1][inside] - xy0[inside], axis=0)
        dc = b1[2] - b0[2]
        agree.append(np.linalg.norm(step - dc) <= tol * np.linalg.norm(dc) + tol_px)
    return float(np.mean(agree)) if agree else float("nan")


def blob_tracks(dynamic: np.ndarray, depth: np.ndarray, threshold: float = 0.5, exclude_uv: np.ndarray | None = None,
                min_px: int = 30, min_solidity: float = 0.85, min_roundness: float = 0.4, size_tol: float = 1.5,
                max_jump_px: float = 20.0, max_gap: int = 10, min_frames: int = 8, seed_frames: int = 6, per_seed_frame: int = 200,
                flow_xy: np.ndarray | None = None, flow_vis: np.ndarray | None = None,
                min_agree: float = 0.7, turn: bool = True, front: float = 0.15,
                focal: np.ndarray | None = None) -> Tracks | None:
    """Tracks on the compact moving blobs, moved by their centroids' paths (module docstring).

    Parameters
    ----------
    dynamic : float [F, H, W] dynamic prior (frames in time order); depth : float [F, H, W]
        the depth the moving pixels have (0 = unknown).
    threshold : a pixel is moving where ``dynamic`` reaches it.
    exclude_uv : float [F, M, 2] or None: points (px; NaN = none) whose blobs get none (the
        projections of hinges: a hinge's blob has tracks along its rings).
    min_px : smallest blob; min_solidity : area over convex hull area a blob must reach in
        most of its path's frames (and in each frame it is seen); min_roundness : minor over
        major axis it must reach in most of them (an elongated blob, a rod or a limb, turns as
        it moves: its centroid is not its points' path); size_tol : a blob continues a path
        within this factor of the path's last three areas; max_jump_px : farthest the centroid
        may land from its prediction per frame; max_gap : frames a path may skip; min_frames :
        shortest path (frames seen) and track kept.
    seed_frames : frames each path seeds tracks from (evenly spread); per_seed_frame : tracks
        per path and seed frame (evenly thinned).
    flow_xy, flow_vis : float [P, F, 2], bool [P, F] or None: the flow's tracks; with them a path
        is kept only where its centroid steps as the tracks inside the blob do in ``min_agree``
        of its steps (:func:`_moves_with_its_pixels`; a path no track reaches is dropped).
    turn : with the flow's tracks, the blob also turns as a sphere (:mod:`engine.priors.blob_turn`):
        its tracks are points of that sphere, seen while they face the camera (their depth
        along the sphere below ``-front`` radii); a path whose turn no step shows, or whose fits
        explain the tracks no better than the noise (:func:`~engine.priors.blob_turn.turn_path`),
        keeps the translation alone.
    focal : float [F] or None: the focal length (px); a turned track's depth is then its point's on
        that sphere (the blob's median depth taken as that of a point 0.71 radii in front of the
        centre, the median over a hemisphere's disc), else the blob's.

    Returns
    -------
    :class:`~engine.priors.tracks.Tracks` with ``depth [P, F]`` (the blob's median depth where
    visible, smoothed over its frames, NaN elsewhere), ``translation_only`` True on the tracks that
    only translate (all of them without ``turn``) and ``query_frame`` the seed frame; None when
    there are none.
    """
    f, h, w = dynamic.shape
    moving = dynamic >= threshold
    frames = [_blobs(moving[k], min_px) for k in range(f)]
    labels = [fr[0] for fr in frames]
    blobs = [fr[1] for fr in frames]
    if exclude_uv is not None:  # a blob holding a hinge has tracks along its rings
        from .hinge import blob_holding

        held = [{blob_holding(labels[k], uv) for uv in exclude_uv[k] if np.isfinite(uv).all()} for k in range(f)]
        blobs = [[b for b in bl if b[0] not in held[k]] for k, bl in enumerate(blobs)]
    paths, turned = [], []  # (xy [P, F, 2], seen [F] or [P, F], depth [F], seed frame) per path and seed frame
    for path in _chains(blobs, max_jump_px, size_tol, max_gap):  # paths (a few)
        if len(path) < min_frames:
            continue
        pf = np.array([k for k, _ in path])
        blob = [blobs[k][i] for k, i in path]
        if np.median([b[3] for b in blob]) < min_solidity or np.median([b[4] for b in blob]) < min_roundness:
            continue
        if flow_xy is not None and not _moves_with_its_pixels(labels, blob, pf, flow_xy, flow_vis) >= min_agree:
            continue
        centre = np.full((f, 2), np.nan)
        z = np.full(f, np.nan)
        for k, b in zip(pf, blob):  # path frames
            centre[k] = b[2]
            zs = depth[k][(labels[k] == b[0]) & (depth[k] > 0)]
            z[k] = np.median(zs) if len(zs) else np.nan
        # seen only where the blob is, compact: a bridged frame (merged, or lost) links the two
        # sides of one track without a position of its own
        on = np.zeros(f, bool)
        on[pf] = np.isfinite(z[pf]) & (np.array([b[3] for b in blob]) >= min_solidity)
        if on.sum() < min_frames:
            continue
        z[on] = _smooth_log(np.nonzero(on)[0], z[on])
        rot = radius = None
        if turn and flow_xy is not None:
            label = np.zeros(f, np.int64)
            label[pf] = [b[0] for b in blob]
            # one physical size: the disc radius of the blob's area times its depth, held over the path
            radius = float(np.median([np.sqrt(b[1] / np.pi) * z[k] for k, b in zip(pf, blob) if on[k]])) / z
            turns, gain = step_turns(labels, label, centre, radius, on, flow_xy, flow_vis)
            rot = turn_path(turns, int(pf[0]), int(pf[-1]), gain)
        seeds = pf[np.unique(np.linspace(0, len(pf) - 1, min(seed_frames, len(pf))).round().astype(np.int64))]
        for s in seeds:  # seed frames (a few)
            lab = blob[int(np.nonzero(pf == s)[0][0])][0]
            ys, xs = np.nonzero(labels[s] == lab)
            keep = np.unique(np.linspace(0, len(xs) - 1, min(per_seed_frame, len(xs))).astype(np.int64))
            off = np.stack([xs[keep] + 0.5, ys[keep] + 0.5], 1) - centre[s]  # [P, 2]
            if rot is None:
                scale = np.where(on, z[s] / np.where(z > 0, z, np.nan), np.nan)  # [F]
                xy = centre[None] + off[:, None] * scale[None, :, None]  # [P, F, 2]
                paths.append((xy, on, z, int(s)))
                continue
            unit = sphere_points(off / radius[s])  # [P, 3] on the unit sphere at the seed frame
            at = np.einsum("fij,kj,pk->pfi", rot, rot[s], unit)  # R(t) R(s)^T: [P, F, 3]
            xy = centre[None] + at[..., :2] * radius[None, :, None]
            # a sphere's points lie at their own depths: the node rotations fitted to the lifted
            # tracks see a turning ball, not a flat disc sliding its texture
            zp = z if focal is None else z[None] + (radius * z / focal)[None] * (at[..., 2] + np.sqrt(0.5))
            turned.append((xy, on[None] & (at[..., 2] < -front), zp, int(s)))
    moved = tracks_from_paths(paths, w, h, min_frames, translation_only=True)
    rolled = tracks_from_paths(turned, w, h, min_frames)
    return moved if rolled is None else concat_tracks(rolled, moved)
