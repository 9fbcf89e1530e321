"""Hinges: static points a moving object turns about, and the depth they give it.

The weight-free depth sees only the static scene, so a moving object first takes the depth
of what is behind it. Ground contact (:func:`engine.priors.dynamic_depth.ground_contact_depth`)
repairs an object that stands on the static scene; one that hangs in the air -- a pendulum,
a swinging sign, an arm waved from a still body -- has only the wall behind it below it, and
keeps a depth that is too far (the generated large-motion scenes' pendulum: 21-70 %). Its
pivot is a *static* point that is on the object in every frame. Under a camera that
translates, only one depth along the pivot's ray keeps its projection on the object's moving
pixels in every frame; at any other depth the camera's parallax walks it off them.

:func:`find_hinges` searches for such points: moving pixels of a few reference frames,
lifted at a range of depths in front of the prior's (which is the background behind them),
are projected into every frame; a candidate is a hinge where it lands on the (slightly
dilated) moving pixels of almost every frame that sees it, only in a narrow depth band (the
score falls on both sides: a camera that does not translate gives no band and no hinge), and
in front of the static surface it covers. Candidates from different reference frames that
agree in 3D are one hinge. :func:`hinge_depth` paints each frame's moving blob that holds a
hinge's projection, near it, with the hinge's camera depth: as ground contact, the object is
taken to be about as far as the point that holds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..geometry.camera import project, unproject


@dataclass
class Hinges:
    """``points [M, 3]`` world hinges; ``support [M]`` candidates that agree on each;
    ``frames [M]`` how many reference frames found it."""

    points: np.ndarray
    support: np.ndarray
    frames: np.ndarray

    def project(self, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every hinge in every frame: ``(uv [F, M, 2] px, z [F, M] camera depth)``, float64,
        for cameras ``K [F, 3, 3]``, ``w2c [F, 4, 4]``."""
        as64 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
        uv, z = project(as64(K)[:, None], as64(w2c)[:, None], as64(self.points)[None])
        return uv.numpy(), z.numpy()


def _candidates(depth, moving, refs, max_per_frame):
    """Moving pixels with a depth in the reference frames, evenly thinned:
    ``(uv [N, 2] continuous px, depth [N], frame [N], blob [N])``; ``blob`` numbers the
    8-connected moving blobs of all reference frames together."""
    from scipy import ndimage

    uv, d, fr, bl = [], [], [], []
    first = 0
    for r in refs:
        labels, n = ndimage.label(moving[r], structure=np.ones((3, 3), bool))
        ys, xs = np.nonzero(moving[r] & (depth[r] > 0) & np.isfinite(depth[r]))
        if not len(ys):
            continue
        keep = np.linspace(0, len(ys) - 1, min(len(ys), max_per_frame)).astype(np.int64)
        ys, xs = ys[keep], xs[keep]
        uv.append(np.stack([xs + 0.5, ys + 0.5], 1)); d.append(depth[r, ys, xs]); fr.append(np.full(len(ys), r))
        bl.append(first + labels[ys, xs]); first += n + 1
    if not uv:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(uv), np.concatenate(d), np.concatenate(fr), np.concatenate(bl)


def _scores(points, K, w2c, on_moving, depth, front):
    """Per world point ``points [S, N, 3]``: the share of frames seeing it that see it on
    ``on_moving [F, H, W]`` (``hit [S, N]``), the share of frames that see it at all
    (``seen [S, N]``) and the share of those where it is not behind the prior ``depth``
    scaled by ``front`` (``ahead [S, N]``)."""
    f, h, w = on_moving.shape
    uv, z = project(K[:, None, None], w2c[:, None, None], points[None])  # [F, S, N, 2], [F, S, N]
    u = torch.floor(uv[..., 0]).long()
    v = torch.floor(uv[..., 1]).long()
    seen = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    fi = torch.arange(f).view(f, 1, 1).expand_as(u)
    uc, vc = u.clamp(0, w - 1), v.clamp(0, h - 1)
    hit = seen & on_moving[fi, vc, uc]
    behind_of = depth[fi, vc, uc]
    known = seen & (behind_of > 0)
    ahead = known & (z <= front * behind_of)
    n_seen = seen.sum(0).clamp_min(1)
    return (hit.sum(0) / n_seen, seen.float().mean(0),
            ahead.sum(0) / known.sum(0).clamp_min(1))


def find_hinges(depth: np.ndarray, dynamic: np.ndarray, K: np.ndarray, w2c: np.ndarray, threshold: float = 0.5,
                ref_frames: int = 6, max_per_frame: int = 400, scale_range: tuple = (0.1, 1.5), num_scales: int = 48,
                accept_range: tuple = (0.15, 1.0), min_hit: float = 0.95, min_seen: float = 0.8, band: float = 1.4,
                drop: float = 0.7, front: float = 1.0, dilate_px: int = 2, merge: float = 0.05, min_refs: float = 0.6,
                max_share: float = 0.5, min_support: float = 0.5, min_candidates: int = 20,
                max_elements: int = 2_000_000) -> Hinges:
    """Static 3D points that every frame sees on its moving pixels.

    Parameters
    ----------
    depth : float [F, H, W] weight-free depth (camera z, 0 = unknown; on moving pixels the
        static scene behind them); dynamic : float [F, H, W] dynamic prior in [0, 1].
    K : [F, 3, 3]; w2c : [F, 4, 4] (OpenCV, continuous pixels), frames in time order.
    threshold : a pixel is moving where ``dynamic >= threshold``.
    ref_frames, max_per_frame : candidates are at most ``max_per_frame`` moving pixels of each
        of ``ref_frames`` evenly spaced frames.
    scale_range, num_scales : the depths tried, as factors of the prior's depth (log-spaced).
    accept_range : a hinge's factor must lie in it (1 = the background's depth: not in front).
    min_hit : share of the frames that see a candidate that must see it on moving pixels.
    min_seen : share of all frames that must see it (in view, in front of the camera).
    band, drop : the hit share must fall to ``drop`` or below at factors ``band`` times smaller
        and larger (a narrow depth band: parallax decides it).
    front : it must not be behind ``front`` x the prior's depth where it projects (occlusion order).
    dilate_px : the moving pixels are dilated by this much (the prior's edge is ragged).
    merge, min_refs : candidates within ``merge`` x their camera depth are one hinge, kept when
        found from at least this share of the reference frames (a pivot is on its object in
        every frame, so every reference frame should find it; on the demo scene the spurious
        ones came from 2-3 of 6, the large scenes' pendulum pivots from 5-6).
    max_share : ... and when at most this share of their blobs' candidates stay on the moving
        pixels at some depth (a blob that does so whole is an object whose motion mimics a
        static one, not one turning about a point).
    min_support, min_candidates : hinges with fewer than this share of the strongest one's
        candidates, or fewer than ``min_candidates``, are dropped.
    max_elements : candidates are scored in chunks of at most this many (frame, depth, candidate)
        projections (~100 bytes each at the peak: a long clip does not grow the memory).

    Returns
    -------
    :class:`Hinges` (possibly empty), strongest support first.
    """
    from scipy import ndimage

    f = depth.shape[0]
    empty = Hinges(np.zeros((0, 3), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))
    moving = dynamic >= threshold
    if f < 3 or not moving.any():
        return empty
    on_moving = moving
    if dilate_px > 0:
        on_moving = ndimage.binary_dilation(moving, structure=np.ones((1, 2 * dilate_px + 1, 2 * dilate_px + 1), bool))
    refs = np.unique(np.linspace(0, f - 1, min(ref_frames, f)).round().astype(np.int64))
    uv, d0, fr, blob = _candidates(depth, moving, refs, max_per_frame)
    if not len(uv):
        return empty
    scales = np.geomspace(scale_range[0], scale_range[1], num_scales)
    Kt, Wt = torch.as_tensor(K, dtype=torch.float64), torch.as_tensor(w2c, dtype=torch.float64)
    mov_t, dep_t = torch.as_tensor(on_moving), torch.as_tensor(np.nan_to_num(depth), dtype=torch.float64)
    s_t = torch.as_tensor(scales, dtype=torch.float64)
    hit, seen, ahead, pts = [], [], [], []
    chunk = max(1, int(max_elements) // (f * num_scales))
    for a in range(0, len(uv), chunk):  # chunks of candidates bound the [F, S, n] arrays
        b = slice(a, a + chunk)
        fk = torch.as_tensor(fr[b])
        z = torch.as_tensor(d0[b], dtype=torch.float64)[None] * s_t[:, None]  # [S, n]
        x = unproject(Kt[fk][None].expand(len(scales), -1, -1, -1), Wt[fk][None].expand(len(scales), -1, -1, -1),
                      torch.as_tensor(uv[b], dtype=torch.float64)[None].expand(len(scales), -1, -1), z)
        h_, s_, a_ = _scores(x, Kt, Wt, mov_t, dep_t, front)
        hit.append(h_); seen.append(s_); ahead.append(a_); pts.append(x)
    hit, seen, ahead = (torch.cat(t, 1).numpy() for t in (hit, seen, ahead))
    pts = torch.cat(pts, 1).numpy()  # [S, N, 3]
    n = hit.shape[1]
    best = hit.max(0)
    # the middle of the run of best scores: a wide plateau is caught by the band test below
    at_best = hit >= best[None] - 1e-9
    first = np.argmax(at_best, 0)
    last = num_scales - 1 - np.argmax(at_best[::-1], 0)
    k = (first + last) // 2
    step = np.log(scales[1] / scales[0])
    off = int(np.ceil(np.log(band) / step))
    lo_i, hi_i = k - off, k + off
    inside = (lo_i >= 0) & (hi_i < num_scales)
    cols = np.arange(n)
    narrow = inside & (hit[np.clip(lo_i, 0, num_scales - 1), cols] <= drop) \
        & (hit[np.clip(hi_i, 0, num_scales - 1), cols] <= drop)
    s_best = scales[k]
    ok = (best >= min_hit) & (seen[k, cols] >= min_seen) & (ahead[k, cols] >= min_hit) & narrow \
        & (s_best >= accept_range[0]) & (s_best <= accept_range[1])
    if not ok.any():
        return empty
    cand = pts[k[ok], cols[ok]]
    cand_ref, cand_blob = fr[ok], blob[ok]
    # share of each blob's candidates that pass: a pivot is a few points of its object; a
    # blob that passes nearly whole moves as a static object would at another depth (the
    # camera's own motion mimicked, e.g. a car driven beside a tracking camera): no hinge
    # (passing = on its moving pixels in nearly every frame at some depth, narrow band or not)
    passing = (best >= min_hit) & (ahead[k, cols] >= min_hit)
    n_blobs = blob.max() + 1
    accepted = np.bincount(blob[passing], minlength=n_blobs) / np.maximum(np.bincount(blob, minlength=n_blobs), 1)
    cand_z = (d0 * s_best)[ok]
    # greedy grouping: the candidate with most agreeing neighbours seeds a hinge, its group leaves
    d2 = ((cand[:, None] - cand[None]) ** 2).sum(-1)
    near = d2 <= (merge * np.minimum(cand_z[:, None], cand_z[None])) ** 2
    left = np.ones(len(cand), bool)
    points, support, frames = [], [], []
    while left.any():
        counts = (near & left[None]).sum(1) * left
        i = int(np.argmax(counts))
        group = near[i] & left
        left &= ~group
        refs_hit = len(np.unique(cand_ref[group]))
        enough_refs = refs_hit >= max(2, int(np.ceil(min_refs * len(refs))))
        if enough_refs and np.median(accepted[cand_blob[group]]) <= max_share:
            points.append(np.median(cand[group], 0)); support.append(int(group.sum())); frames.append(refs_hit)
    if not points:
        return empty
    # weak groups are the fringe of a wide motion mask (a point floating in front of the wall
    # that the swept object's dilated mask covers from every view): on the generated scenes and
    # the demo clip they had 5-15 candidates against the pivots' 26-108
    keep = np.asarray(support) >= max(min_support * max(support), min_candidates)
    points, support, frames = (list(np.asarray(a)[keep]) for a in (points, support, frames))
    order = np.argsort(-np.asarray(support), kind="stable")
    return Hinges(np.asarray(points, np.float32)[order], np.asarray(support, np.int64)[order],
                  np.asarray(frames, np.int64)[order])


def blob_holding(labels: np.ndarray, uv: np.ndarray, search_px: int = 3) -> int:
    """The label of the blob that holds a hinge projected at ``uv [2]`` (continuous px): the
    label most common among the labelled pixels within ``search_px`` of it; 0 for none.
    ``labels [H, W]`` int (0 = background, :func:`scipy.ndimage.label`)."""
    cx, cy = int(np.floor(uv[0])), int(np.floor(uv[1]))
    if cx + search_px < 0 or cy + search_px < 0:
        return 0
    win = labels[max(cy - search_px, 0):cy + search_px + 1, max(cx - search_px, 0):cx + search_px + 1]
    win = win[win > 0]
    return int(np.bincount(win).argmax()) if len(win) else 0


def hinge_depth(hinges: Hinges, dynamic: np.ndarray, K: np.ndarray, w2c: np.ndarray, threshold: float = 0.5,
                search_px: int = 3, merged: float = 1.3, depth: np.ndarray | None = None,
                near: float = 0.6) -> tuple[np.ndarray, dict]:
    """Each hinge's camera depth on the moving blob that holds it, frame by frame.

    A frame's blob holding a hinge is the 8-connected component of moving pixels most common
    within ``search_px`` of the hinge's projection. Only its pixels within the hinge's reach
    are painted: the median over frames of the distance from the hinge to its blob's farthest
    pixel; and frames whose blob is over ``merged`` x its median size (the object touches
    another moving thing there) are skipped, so that the other object keeps its own depth.
    Where two hinges paint a pixel, the one with more support wins: hinges on one blob are
    the same pivot's depth ambiguity near it (points next to a pivot stay on the swept object
    at a range of depths), and the strongest is the best determined. With the prior ``depth
    [F, H, W]`` given, only pixels it puts beyond ``1 / near`` times the hinge's depth are
    painted: a part floating well in front of the surface the prior sees there. Where the
    prior is about as near as the hinge, it saw the object itself (a large slow flag whose
    own tracks triangulate; its pole is the hinge, its free edge nearer or farther) or
    another object shares the blob (an arm beside the flag on the generated scenes), and
    the prior is the better guess.

    Returns
    -------
    depth float32 [F, H, W] (NaN where no hinge paints) and ``{"hinges", "painted_px", "frames"}``.
    """
    from scipy import ndimage

    f, h, w = dynamic.shape
    out = np.full((f, h, w), np.nan, np.float32)
    stats = {"hinges": int(len(hinges.points)), "painted_px": 0, "frames": 0}
    if not len(hinges.points):
        return out, stats
    uv, z = hinges.project(K, w2c)  # [F, M, 2], [F, M]
    moving = dynamic >= threshold
    ys, xs = np.mgrid[0:h, 0:w]

    def blobs(k):
        """``(hinge, blob mask, distance map)`` for each hinge seen on a blob of frame ``k``."""
        labels, n = ndimage.label(moving[k], structure=np.ones((3, 3), bool))
        for m in range(len(hinges.points) if n else 0):
            lab = blob_holding(labels, uv[k, m], search_px) if z[k, m] > 0 else 0
            if lab:
                yield m, labels == lab, np.hypot(xs + 0.5 - uv[k, m, 0], ys + 0.5 - uv[k, m, 1])

    # two passes over the frames (labelling is cheap; keeping every blob mask is not)
    far, size = [[] for _ in hinges.points], [[] for _ in hinges.points]
    for k in range(f):
        for m, blob, dist in blobs(k):
            far[m].append(float(dist[blob].max())); size[m].append(int(blob.sum()))
    reach = [float(np.median(d)) if d else 0.0 for d in far]
    largest = [merged * float(np.median(a)) if a else 0.0 for a in size]
    for k in range(f):
        for m, blob, dist in blobs(k):
            if blob.sum() > largest[m]:  # merged with another moving thing: that one keeps its own depth
                continue
            paint = blob & (dist <= reach[m]) & np.isnan(out[k])  # hinges come strongest first
            if depth is not None:
                paint &= depth[k] * near > z[k, m]
            out[k][paint] = z[k, m]
    painted = np.isfinite(out)
    stats["painted_px"] = int(painted.sum())
    stats["frames"] = int(painted.any((1, 2)).sum())
    return out, stats
