"""A depth for moving objects that stays with them: one depth per track, spread over the
moving pixels of every frame.

The weight-free depth (:func:`engine.priors.estimate_depth`) cannot see moving objects:
its anchors are triangulated static tracks, so a moving object's pixels take the depth of
the static surfaces around and behind it, which changes from frame to frame as the object
crosses the scene (a ball rolling past a wall and then the floor "jumps" in depth). Lifted
with that depth, a 2D track on the object carries made-up motion along the ray, nodes
seated at different frames disagree on where the object is, and Gaussians back-projected
from different frames land at different depths -- the object smears into a ghost.

:func:`track_consistent_depth` gives every moving track one depth -- a low percentile of the
prior along the track -- and paints each moving pixel of each frame with the depth of the
nearest moving track visible there. Given the cameras, that one depth is the depth of the
track's point at its reference frame, and at the other frames it is the depth that point
would have if it had stayed where it was: the change the camera's own motion makes (the
generated scenes' orbiting camera changes a point's depth 1.1-1.5x over a clip). Lifted
tracks then move only across the rays (the motion the image shows), and candidates, nodes,
tracks and Gaussians seeded from any frame agree. Used only with the weight-free depth;
a depth model or file sees the objects and is kept as it is. :func:`moving_object_depth`
runs the stages in order for ``engine.pipeline.prepare``: ground contact, hinges
(:mod:`engine.priors.hinge`), one depth per track, and the hinges' own long tracks
(:mod:`engine.priors.hinge_tracks`, appended after the per-track depth: they carry theirs).
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


def _first_static_below(depth: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """``[F, H, W]``: for every pixel, the depth of the first non-moving pixel with a known
    depth strictly below it in its column (NaN where there is none). One pass over the rows,
    vectorised over frames and columns."""
    f, h, w = depth.shape
    static = np.where(~moving & (depth > 0) & np.isfinite(depth), depth, np.nan).astype(np.float32)
    out = np.full((f, h, w), np.nan, np.float32)
    below = np.full((f, w), np.nan, np.float32)
    for y in range(h - 1, -1, -1):  # bottom-up scan: rows, not pixels
        out[:, y] = below
        below = np.where(np.isfinite(static[:, y]), static[:, y], below)
    return out


def ground_contact_depth(depth: np.ndarray, dynamic: np.ndarray, threshold: float = 0.5,
                         band_px: int = 3, min_px: int = 12, margin_px: int = 4) -> tuple[np.ndarray, dict]:
    """The depth at which each moving blob of each frame touches the static scene below it.

    Parameters
    ----------
    depth : float [F, H, W] weight-free depth (camera z; 0 = unknown), which sees the static
        scene only; dynamic : float [F, H, W] dynamic prior in [0, 1].
    threshold : a pixel is moving where ``dynamic >= threshold``.
    band_px : the blob's contact rows: its lowest ``band_px`` rows.
    min_px : blobs smaller than this (noise in the prior) get no contact depth.

    Returns
    -------
    contact float32 [F, H, W]: on the pixels of each moving blob (8-connected), the median
    over its lowest rows of the depth of the first static pixel below; NaN elsewhere and for
    blobs that touch the bottom edge of the image (their contact is out of view). And stats
    ``{"blobs", "with_contact"}``.

    Image "down" is taken as the ground's direction (footage is shot about upright). A blob
    hanging in the air gets the depth of the surface beneath it in the image, which for a
    wall behind it is the prior's own value: the caller keeps the smaller of the two.
    """
    from scipy import ndimage

    moving = dynamic >= threshold
    grown = moving
    if margin_px > 0:  # the prior's blob edge is ragged: look past a margin of it
        grown = ndimage.binary_dilation(moving, structure=np.ones((1, 2 * margin_px + 1, 2 * margin_px + 1), bool))
    below = _first_static_below(depth, grown)
    f, h, w = depth.shape
    contact = np.full((f, h, w), np.nan, np.float32)
    stats = {"blobs": 0, "with_contact": 0}
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    for k in range(f):  # per frame, every blob at once through ndimage's labelled reductions
        labels, n = ndimage.label(moving[k], structure=np.ones((3, 3), bool))
        if n == 0:
            continue
        ids = np.arange(1, n + 1)
        size = np.bincount(labels.ravel(), minlength=n + 1)[1:]
        bottom = ndimage.maximum(rows, labels, ids).astype(np.int64)
        lab_bottom = np.concatenate([[-1], bottom])[labels]
        band = (labels > 0) & (rows >= lab_bottom - band_px + 1) & np.isfinite(below[k])
        band_labels = np.where(band, labels, 0)
        with np.errstate(all="ignore"):
            med = np.asarray(ndimage.median(np.nan_to_num(below[k]), band_labels, ids), np.float64)
        has_band = ndimage.sum_labels(band, band_labels, ids) > 0
        ok = has_band & (size >= min_px) & (bottom < h - 1)
        value = np.concatenate([[np.nan], np.where(ok, med, np.nan)]).astype(np.float32)
        contact[k] = np.where(labels > 0, value[labels], np.nan)
        stats["blobs"] += int(n)
        stats["with_contact"] += int(ok.sum())
    return contact, stats


def track_consistent_depth(depth: np.ndarray, dynamic: np.ndarray, xy: np.ndarray, visible: np.ndarray,
                           threshold: float = 0.5, max_px: float | None = None,
                           contact: np.ndarray | None = None, percentile: float = 10.0,
                           K: np.ndarray | None = None, w2c: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Depth with one value per moving track, spread to the moving pixels of each frame.

    Without cameras a track's depth is the same at every frame; with them (``K``, ``w2c``) it
    is one depth at the track's reference frame (the visible frame nearest the middle of its
    life), carried to the other frames as the camera depth of that point left at rest
    (:func:`_rest_depth_lines`): the prior's depths along the track are taken back to the
    reference frame the same way before the percentile, so the camera's approach or retreat
    is neither mistaken for the object's depth nor averaged away. A point at rest is then
    lifted to one place; a moving one moves across the rays as before.

    Parameters
    ----------
    depth : float [F, H, W] (0 = unknown); dynamic : float [F, H, W] dynamic prior;
    xy : float [P, F, 2] track pixels; visible : bool [P, F]; frames in time order.
    threshold : a pixel / track is moving where the prior is at least this.
    max_px : moving pixels farther than this from every moving track visible in their
        frame keep their depth (default: 1/8 of the image diagonal).
    percentile : which percentile of the depths seen along a track is its depth (10: the
        nearest surface it was seen in front of, with some robustness; 50: the median).
    contact : float [F, H, W] or None: a ground-contact depth of the moving blobs
        (:func:`ground_contact_depth`, NaN = none); where given, a track's depth at a frame
        is the smaller of it and the prior (occlusion order), and moving pixels far from
        every track take it too.
    K : float [F, 3, 3], w2c : float [F, 4, 4] or None: the frames' cameras (both or neither).

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
    if contact is not None:
        # moving pixels no track reaches still stand on their contact (and in front of the wall)
        far = np.isfinite(contact) & (dynamic >= threshold) & (out > 0)
        out[far] = np.minimum(out[far], contact[far])
    if not moving.any():
        return out, stats
    mxy, mvis = xy[moving], visible[moving]
    z = _along_tracks(depth, mxy)
    z = np.where(mvis & (z > 0) & np.isfinite(z), z, np.nan)
    if contact is not None:
        zc = _along_tracks(contact, mxy)
        z = np.where(np.isfinite(zc) & np.isfinite(z), np.minimum(z, zc), z)
    # the camera depth at frame k of a track's point left at rest is a + b z, z its depth at the
    # reference frame; without cameras a = 0, b = 1: one depth for the track's whole life
    a, b = _rest_depth_lines(mxy, mvis, K, w2c) if w2c is not None else (np.zeros_like(z), np.ones_like(z))
    with np.errstate(all="ignore"):
        # each frame's depth taken back to the reference frame (b small: the reference ray runs
        # nearly parallel to that frame's image plane, and the inverse is unstable); then a low
        # percentile in log depth: the object is in front of everything the prior saw behind it
        # along the track (occlusion order), robust to a few stray frames; the median (50) is
        # the typical background depth, the former choice
        z_ref = np.where(b > 0.2, (z - a) / b, np.nan)
        z_ref = np.exp(np.nanpercentile(np.log(np.where(z_ref > 0, z_ref, np.nan)), percentile, axis=1))
        z_pf = a + b * z_ref[:, None]  # [P, F]
    z_pf = np.where(np.isfinite(z_pf) & (z_pf > 0), z_pf, np.nan)
    for k in range(f):  # one KD-tree per frame; every pixel query of the frame is vectorised
        on = mvis[:, k] & np.isfinite(z_pf[:, k])
        ys, xs = np.nonzero(dynamic[k] >= threshold)
        if not on.any() or not len(ys):
            continue
        tree = cKDTree(mxy[on, k])
        dist, j = tree.query(np.stack([xs + 0.5, ys + 0.5], 1), k=1)
        near = dist <= max_px
        out[k, ys[near], xs[near]] = z_pf[on, k][j[near]].astype(np.float32)
        stats["painted_px"] += int(near.sum())
        stats["frames"] += 1
    return out, stats


def _rest_depth_lines(xy: np.ndarray, visible: np.ndarray, K: np.ndarray, w2c: np.ndarray):
    """``(a, b)`` float [P, F]: the camera depth at frame k of a track's point left at rest where
    it was at its reference frame (the middle of its visible frames) at depth z there is
    ``a + b z`` (camera depth is affine along a ray): the depth change that the camera's own
    motion makes. ``xy [P, F, 2]``, ``visible [P, F]``, ``K [F, 3, 3]``, ``w2c [F, 4, 4]``."""
    import torch

    from ..geometry.camera import camera_centers, unproject, world_to_camera

    p, f = visible.shape
    frame = np.arange(f)[None]
    first = np.where(visible, frame, f).min(1)
    last = np.where(visible, frame, -1).max(1)
    mid = (first + last) // 2
    # the visible frame nearest the middle of the track's span (a never-visible track: frame 0)
    ref = np.argmin(np.where(visible, np.abs(frame - mid[:, None]), f + 1), axis=1)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float64)
    Wt = torch.as_tensor(np.asarray(w2c), dtype=torch.float64)
    rt = torch.as_tensor(ref)
    uv = torch.as_tensor(np.nan_to_num(xy[np.arange(p), ref]), dtype=torch.float64)
    x1 = unproject(Kt[rt], Wt[rt], uv, torch.ones(p, dtype=torch.float64))  # [P, 3] at depth 1
    c = camera_centers(Wt)[rt]  # [P, 3]
    a = world_to_camera(Wt[None], c[:, None])[..., 2]  # [P, F]
    b = world_to_camera(Wt[None], x1[:, None])[..., 2] - a
    return a.numpy(), b.numpy()


HINGE_MODES = ("auto", "depth", "off")


def moving_object_depth(pr, prior_config, K, w2c, extent, reporter) -> tuple[np.ndarray, object, dict]:
    """The weight-free depth with a depth of their own for moving objects, the tracks with
    those of the hinges, and what gave them.

    The weight-free depth of a moving object is its surroundings' and changes as the object
    crosses them: each moving track gets one depth (:func:`track_consistent_depth`, carried
    over its frames as the cameras move), from
    ground contact and occlusion order ('contact', :func:`ground_contact_depth`) and, for an
    object that turns about a static point, that point's depth where nearer
    (:mod:`engine.priors.hinge`); with ``hinges`` 'auto' such an object also gets long tracks
    along its rings (:mod:`engine.priors.hinge_tracks`; 'depth': the depth only), and with
    ``blob_tracks`` 'auto' a compact moving blob long tracks along its path
    (:mod:`engine.priors.blob_tracks`). ``pr`` : the
    clip's :class:`~engine.priors.cache.Priors`; ``prior_config`` : its ``PriorConfig``;
    ``K [F,3,3]``, ``w2c [F,4,4]`` : the cameras of its frames; ``extent`` : the scene's
    (:func:`engine.geometry.camera.scene_extent`, which ``prepare`` has already);
    ``reporter`` : what logs the stages. Returns ``(depth [F,H,W], tracks, record)``: ``tracks``
    is ``pr.tracks`` with the hinge and blob tracks appended (:class:`~engine.priors.tracks.Tracks`),
    ``record`` for scene.json's ``priors.depth``.
    """
    mode = prior_config.moving_depth
    if mode not in ("contact", "track"):
        raise ValueError(f"PriorConfig.moving_depth must be 'contact' or 'track', not {mode!r}")
    if prior_config.hinges not in HINGE_MODES:
        raise ValueError(f"PriorConfig.hinges must be one of {HINGE_MODES}, not {prior_config.hinges!r}")
    if prior_config.blob_tracks not in ("auto", "off"):
        raise ValueError(f"PriorConfig.blob_tracks must be 'auto' or 'off', not {prior_config.blob_tracks!r}")
    record = {"moving_objects": mode}
    contact = hinges = None
    if mode == "contact":
        contact, cst = ground_contact_depth(pr.depth, pr.dynamic)
        reporter.log(f"moving objects: ground contact found for {cst['with_contact']} of {cst['blobs']} "
                     "moving blobs")
        if prior_config.hinges != "off":
            contact, hinges = _with_hinges(contact, pr.depth, pr.dynamic, K, w2c, extent, reporter)
            record["hinges"] = 0 if hinges is None else int(len(hinges.points))
    depth, st = track_consistent_depth(pr.depth, pr.dynamic, pr.tracks.xy, pr.tracks.visible,
                                       contact=contact, percentile=10.0 if mode == "contact" else 50.0,
                                       K=K, w2c=w2c)
    reporter.log(f"moving objects: one depth per moving track ({st['moving_tracks']} tracks, "
                 f"{st['painted_px']} pixels in {st['frames']} frames)")
    tracks = pr.tracks
    if hinges is not None and prior_config.hinges == "auto":
        from .hinge_tracks import hinge_tracks
        from .tracks import concat_tracks

        more = hinge_tracks(hinges, pr.dynamic, K, w2c)
        record["hinge_tracks"] = 0 if more is None else int(len(more.xy))
        if more is not None:
            reporter.log(f"moving objects: {len(more.xy)} tracks along the hinges' rings (median "
                         f"{int(np.median(more.visible.sum(1)))} frames long)")
            tracks = concat_tracks(tracks, more)
    if mode == "contact" and prior_config.blob_tracks == "auto":
        tracks = _with_blob_tracks(tracks, depth, pr.dynamic, hinges, K, w2c, record, reporter)
    return depth, tracks, record


def _with_blob_tracks(tracks, depth, dynamic, hinges, K, w2c, record, reporter):
    """``tracks`` with those of the compact moving blobs appended (engine/priors/blob_tracks.py;
    a blob holding a hinge has its own), the count in ``record["blob_tracks"]``."""
    from .blob_tracks import blob_tracks
    from .tracks import concat_tracks

    exclude = None
    if hinges is not None:
        uv, z = hinges.project(K, w2c)
        exclude = np.where((z > 0)[..., None], uv, np.nan)  # [F, M, 2]
    more = blob_tracks(dynamic, depth, exclude_uv=exclude, flow_xy=tracks.xy, flow_vis=tracks.visible,
                       focal=np.asarray(K)[:, 0, 0])
    record["blob_tracks"] = 0 if more is None else int(len(more.xy))
    if more is None:
        return tracks
    turning = len(more.xy) if more.translation_only is None else int((~more.translation_only).sum())
    reporter.log(f"moving objects: {len(more.xy)} tracks along compact blobs' paths ({turning} turning with "
                 f"the blob; median {int(np.median(more.visible.sum(1)))} frames long)")
    return concat_tracks(tracks, more)


def _with_hinges(contact, depth, dynamic, K, w2c, extent, reporter):
    """``(contact', hinges or None)``: ``contact [F, H, W]`` with the depth of the hinges found
    (engine/priors/hinge.py) where nearer: a moving object that turns about a static point is
    about as far as that point."""
    import torch

    from ..geometry.camera import camera_translates
    from .hinge import find_hinges, hinge_depth

    if not camera_translates(torch.as_tensor(np.asarray(w2c), dtype=torch.float64), extent):
        return contact, None  # no parallax, no hinge: skip a search (~0.4 s per 10 frames) that finds none
    hinges = find_hinges(depth, dynamic, K, w2c)
    if not len(hinges.points):
        return contact, None
    hd, st = hinge_depth(hinges, dynamic, K, w2c, depth=depth)
    reporter.log(f"moving objects: {st['hinges']} hinge(s) (a static point a moving object turns about) give "
                 f"their depth to {st['painted_px']} pixels in {st['frames']} frames")
    return np.fmin(contact, hd), hinges
