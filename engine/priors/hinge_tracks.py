"""Hinge tracks: long 2D tracks on a body that turns about a hinge, from its moving pixels.

The tracker's flow loses thin, fast parts within a frame or two (a swinging link's tracks
live 1-2 frames on the generated large-motion scenes), so the node paths fitted to them
follow such a part only near the frames the tracks came from (docs/benchmarks.md, *Hinges*).
A hinge (:mod:`engine.priors.hinge`) gives a constraint that needs no flow: a point of a rigid
body turning about a static hinge keeps its distance to it. Lifted at the hinge's camera
depth (what :func:`~engine.priors.hinge.hinge_depth` paints), the moving pixels of the blob
holding the hinge fall in bands of 3D distance to it; in each band the blob is one or a few
short *arcs* across the body. An arc is followed from frame to frame by its angular centroid
about the hinge's projection (its last angular step predicts the next; the nearest arc of the
same band within ``max_jump_px`` continues it, else the path ends), and every pixel of the arc
at the seed frame becomes a track that keeps its angular and radial offset from the arc.

The tracks carry their own camera depth (the hinge's, frame by frame): the per-track depth of
:func:`~engine.priors.dynamic_depth.track_consistent_depth` carries one depth over a track's
life as if its point were at rest, which a link turning about the hinge is not.

A body that is not rigid about the hinge (a second link hanging from the first, a cloth on a
pole) slides along its rings: :func:`hinge_tracks` keeps only the bands whose turn agrees with
their neighbours' (``rigid_tol``) and ends a path where it stops agreeing.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from ..geometry.camera import unproject
from .tracks import Tracks, tracks_from_paths


def _wrap(a):
    """Angles to (-pi, pi]."""
    return np.angle(np.exp(1j * a))


def _frame_pixels(blob, K, w2c, hinge, uv_h, z_h):
    """A blob's pixels about the hinge: ``(uv [N, 2], r [N] 3D distance at the hinge's camera
    depth, angle [N] about the hinge's projection, r_px [N] image distance to it)``."""
    ys, xs = np.nonzero(blob)
    uv = np.stack([xs + 0.5, ys + 0.5], 1)
    as64 = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    world = unproject(as64(K), as64(w2c), as64(uv), torch.full((len(uv),), float(z_h), dtype=torch.float64)).numpy()
    d = uv - uv_h
    return uv, np.linalg.norm(world - hinge, axis=1), np.arctan2(d[:, 1], d[:, 0]), np.hypot(d[:, 0], d[:, 1])


def _arcs(band, angle, r_px, gap_px):
    """Split each band's pixels into arcs (runs of angle without a gap over ``gap_px``).

    Returns ``(arc [N] id per pixel, arc_band [A], arc_angle [A] circular mean, arc_r_px [A])``.
    """
    n = len(band)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    order = np.lexsort((angle, band))
    b, a, rp = band[order], angle[order], r_px[order]
    new = np.ones(n, bool)
    new[1:] = (b[1:] != b[:-1]) | ((a[1:] - a[:-1]) * np.maximum(rp[1:], 1.0) > gap_px)
    ids = np.cumsum(new) - 1
    # an arc across the -pi / pi cut: merge a band's last run into its first
    last_of_band = np.r_[b[1:] != b[:-1], True]
    for end in np.nonzero(last_of_band)[0]:  # one per band (tens), not per pixel
        start = np.searchsorted(b, b[end])
        if ids[end] != ids[start] and (a[start] + 2 * np.pi - a[end]) * max(rp[end], 1.0) <= gap_px:
            ids[ids == ids[end]] = ids[start]
    _, ids = np.unique(ids, return_inverse=True)
    m = ids.max() + 1
    arc_angle = np.angle(np.bincount(ids, np.cos(a), m) + 1j * np.bincount(ids, np.sin(a), m))
    cnt = np.bincount(ids, minlength=m)
    arc_r = np.bincount(ids, rp, m) / cnt
    arc_band = np.zeros(m, np.int64)
    arc_band[ids] = b
    out = np.empty(n, np.int64)
    out[order] = ids
    return out, arc_band, arc_angle, arc_r


def _follow(frames_arcs, seed, f, max_jump_px):
    """Follow every arc of frame ``seed`` through the clip.

    ``frames_arcs[k]``: ``(band [A], angle [A], r_px [A])`` or None. Returns ``angle [S, F]``
    and ``r_px [S, F]`` of each seed arc's path (NaN where it has ended).
    """
    band0, ang0, r0 = frames_arcs[seed]
    s = len(band0)
    ang = np.full((s, f), np.nan)
    rad = np.full((s, f), np.nan)
    ang[:, seed], rad[:, seed] = ang0, r0
    for step in (1, -1):
        theta, omega, alive = ang0.copy(), np.zeros(s), np.ones(s, bool)
        k = seed + step
        while 0 <= k < f and alive.any():  # frames, vectorised over paths
            if frames_arcs[k] is None:
                break
            bk, ak, rk = frames_arcs[k]
            pred = theta + omega
            miss = np.abs(_wrap(ak[None] - pred[:, None])) * rk[None]  # [S, A] px along the ring
            miss[band0[:, None] != bk[None]] = np.inf
            j = miss.argmin(1) if len(bk) else np.zeros(s, np.int64)
            ok = alive & (miss[np.arange(s), j] <= max_jump_px) if len(bk) else np.zeros(s, bool)
            new = np.where(ok, ak[j] if len(bk) else 0.0, theta)
            omega = np.where(ok, _wrap(new - theta), omega)
            theta = new
            ang[ok, k], rad[ok, k] = theta[ok], rk[j[ok]]
            alive = ok
            k += step
    return ang, rad


def _rigid(ang, band, ang0, tol):
    """``[S, F] bool``: where each path's turn since the seed frame agrees (within ``tol``
    radians) with the median turn of the paths in the neighbouring bands (+-2)."""
    turn = _wrap(ang - ang0[:, None])
    ok = np.zeros_like(turn, bool)
    for b in np.unique(band):  # bands (tens)
        mine = band == b
        near = (np.abs(band - b) <= 2) & ~mine
        if not near.any():  # a band alone: nothing to compare with
            ok[mine] = True
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # frames where every neighbour has ended
            ref = np.nanmedian(turn[near], 0)
        # no neighbour to compare with at a frame: nothing says the band slides there
        ok[mine] = ~(np.abs(_wrap(turn[mine] - ref[None])) > tol)
    return ok


def _run_through(ok, seed):
    """Keep, per row of ``ok [S, F]``, only the run of True through column ``seed``."""
    f = ok.shape[1]
    idx = np.arange(f)
    bad = ~ok
    left = np.where(bad & (idx < seed), idx, -1).max(1)
    right = np.where(bad & (idx > seed), idx, f).min(1)
    return ok & (idx[None] > left[:, None]) & (idx[None] < right[:, None])


def hinge_tracks(hinges, dynamic: np.ndarray, K: np.ndarray, w2c: np.ndarray, threshold: float = 0.5,
                 seed_frames: int = 6, per_seed_frame: int = 400, band_px: float = 1.5, gap_px: float = 3.0,
                 max_jump_px: float = 12.0, rigid_tol: float = 0.15, min_frames: int = 4,
                 search_px: int = 3, merged: float = 1.3) -> Tracks | None:
    """Tracks on the blobs that hold hinges, followed along their rings (module docstring).

    Parameters
    ----------
    hinges : :class:`~engine.priors.hinge.Hinges` (world points [M, 3]).
    dynamic : float [F, H, W] dynamic prior (frames in time order); K [F, 3, 3]; w2c [F, 4, 4].
    threshold : a pixel is moving where ``dynamic`` reaches it.
    seed_frames : how many frames start paths, evenly spread over those whose blob holds the
        hinge and touches nothing else.
    per_seed_frame : tracks kept per hinge and seed frame (evenly thinned).
    band_px : band width in pixels at the hinge's depth; gap_px : an arc's largest gap.
    max_jump_px : farthest a path's arc may land from its prediction.
    rigid_tol : radians a path's turn may differ from its neighbour bands'.
    min_frames : shortest track kept.
    search_px : how near the hinge's projection its blob must be (as in ``hinge_depth``).
    merged : a blob over this x its median size touches another moving thing there.

    Returns
    -------
    :class:`~engine.priors.tracks.Tracks` with ``depth [P, F]`` (the hinge's camera depth where
    visible, NaN elsewhere) and ``query_frame`` the seed frame; None when there are none.
    """
    from scipy import ndimage

    from .hinge import blob_holding

    f, h, w = dynamic.shape
    if not len(hinges.points) or f < 2:
        return None
    uv_h, z_h = hinges.project(K, w2c)  # [F, M, 2], [F, M]
    labels = [ndimage.label(dynamic[k] >= threshold, structure=np.ones((3, 3), bool))[0] for k in range(f)]
    held = np.array([[blob_holding(labels[k], uv_h[k, m], search_px) if z_h[k, m] > 0 else 0
                      for m in range(len(hinges.points))] for k in range(f)])  # [F, M] blob label
    size = np.array([[np.count_nonzero(labels[k] == lab) if lab else 0 for lab in row] for k, row in enumerate(held)])
    # hinges come strongest first: a blob a stronger hinge holds is that hinge's (one pivot's
    # depth ambiguity gives several hinges on one blob, as in hinge_depth)
    for m in range(1, held.shape[1]):
        held[:, m] = np.where((held[:, :m] == held[:, m:m + 1]).any(1), 0, held[:, m])
    paths = []  # (xy [P, F, 2], seen [P, F], depth [F], seed frame) per hinge and seed frame
    for m, hinge in enumerate(np.asarray(hinges.points, np.float64)):  # hinges (a few)
        zm = z_h[:, m]
        if not (held[:, m] > 0).any():
            continue
        band_w = band_px * float(np.median(zm[zm > 0])) / float(np.median(K[:, 0, 0]))
        # a blob over `merged` x its median size touches another moving thing: followed through
        # (the arc nearest the prediction decides) but not seeded from (its pixels are not all this body's)
        merged_at = size[:, m] > merged * np.median(size[held[:, m] > 0, m])
        # seed frames evenly spread over the frames that can seed
        can = np.nonzero((held[:, m] > 0) & ~merged_at)[0]
        seeds = can[np.unique(np.linspace(0, len(can) - 1, min(seed_frames, len(can))).round().astype(np.int64))]
        pixels, arcs = [None] * f, [None] * f
        for k in range(f):  # frames
            lab = held[k, m]
            if not lab:
                continue
            uv, r, ang, r_px = _frame_pixels(labels[k] == lab, K[k], w2c[k], hinge, uv_h[k, m], zm[k])
            band = np.floor(r / band_w).astype(np.int64)
            arc, a_band, a_ang, a_r = _arcs(band, ang, r_px, gap_px)
            pixels[k] = (uv, ang, r_px, arc)
            arcs[k] = (a_band, a_ang, a_r)
        for s in seeds:  # seed frames (a few)
            ang, rad = _follow(arcs, int(s), f, max_jump_px)
            a_band, a_ang, a_r = arcs[s]
            alive = np.isfinite(ang) & _run_through(_rigid(ang, a_band, a_ang, rigid_tol) | (np.arange(f) == s), int(s))
            _, p_ang, p_rpx, p_arc = pixels[s]
            keep = np.unique(np.linspace(0, len(p_arc) - 1, min(per_seed_frame, len(p_arc))).astype(np.int64))
            arc = p_arc[keep]
            delta = _wrap(p_ang[keep] - a_ang[arc])[:, None]  # [P, 1] angle from the arc's centroid
            r_off = (p_rpx[keep] - a_r[arc])[:, None] * (zm[s] / np.where(zm > 0, zm, np.nan))[None]
            theta = ang[arc] + delta
            radius = rad[arc] + r_off
            xy = uv_h[None, :, m] + radius[..., None] * np.stack([np.cos(theta), np.sin(theta)], -1)
            paths.append((xy, alive[arc], zm, int(s)))
    return tracks_from_paths(paths, w, h, min_frames)
