"""Metric depth per frame: sparse triangulation + edge-aware densification, or ONNX aligned to anchors.

Anchors: ``anchors`` is a list (one per frame) of ``[A,3]`` arrays (u, v, depth) in
continuous pixel coords / scene units, or ``None``. :func:`anchors_from_tracks` builds them
by DLT-triangulating each track from all its visible frames (vectorised batched SVD), keeping
points with positive depth, enough parallax and a small reprojection error. Points on moving
objects fail the reprojection test (and, if ``dynamic [F,H,W]`` is given, observations with
p_dyn > 0.5 are excluded), so only static structure anchors the depth. A frame with fewer
than ``min_anchors`` own observations uses all triangulated points projected into it.

``sparse`` backend: per frame, edge-aware normalised convolution at <= ``max_width`` px:
``D = FGS(d * c) / FGS(c)`` with ``cv2.ximgproc.fastGlobalSmootherFilter`` guided by the
frame, (in inverse depth). Dynamic regions get no anchors, so they are filled from the
surrounding static depth. No anchors at all -> the median scene depth (confidence 0).

``moving_fill`` (sparse backend, needs ``dynamic``): ``'surround'`` (default) keeps that fill;
``'support'`` (opt-in, :func:`support_fill`) then caps every connected moving region
(``p_dyn > 0.5``) at a low percentile of the depth in a thin ring around it: a moving object
occludes what is around it, so its depth is at most that of its nearest support (e.g. the
floor it stands on), not the mean of the background behind it; it cannot place an object
that floats in front of everything around it. Measured on the generated ``small`` scenes
(seeds 0/1/2), moving-pixel AbsRel with the GT mask passed as ``dynamic``: 0.99/0.94/0.91 ->
0.33/0.31/0.29, static pixels unchanged; :func:`support_fill` applied to the default depth
with the final weight-free motion mask: 0.22/0.21/0.20 -> 0.11/0.11/0.11, but static AbsRel
0.038/0.038/0.040 -> 0.054/0.056/0.057 (the mask's halo takes the object's depth). Not the
default: neither improves the node-trajectory error of ``python -m engine.bench nodes``.

``onnx`` backend: a monocular model (input as in :mod:`onnx_util`; output [B,H,W] or
[B,1,H,W]). ``output`` (argument, else sidecar ``output``, else 'inverse'): 'inverse' for
MiDaS / Depth-Anything style relative inverse depth (larger = nearer), 'depth' for relative
depth (larger = farther, e.g. PyDNet). Input size: sidecar ``input_size``, else the graph's
fixed size, else (dynamic H, W) the frame's aspect at sidecar ``input_width`` or
``max_width`` px, rounded to multiples of sidecar ``size_multiple`` (default 32; PyDNet needs
64). The prediction is aligned per frame with a robust scale+shift fit (IRLS, Huber) against
that frame's anchors (triangulated static tracks: moving points fail the triangulation), in
inverse depth for 'inverse' models and in depth for 'depth' models; moving objects keep the
model's own depth relative to the scene (the weight-free fill only copies their surroundings).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from . import onnx_util


def triangulate_tracks(xy, visible, K, w2c, max_reproj=2.0, min_angle_deg=0.5):
    """DLT triangulation of tracks. ``xy [P,F,2]``, ``visible [P,F]`` -> (X [P,3], ok [P])."""
    P, F = visible.shape
    Pm = np.einsum("fij,fjk->fik", K, w2c[:, :3, :])  # [F,3,4]
    x, y = xy[..., 0:1], xy[..., 1:2]
    A = np.stack([x * Pm[None, :, 2] - Pm[None, :, 0], y * Pm[None, :, 2] - Pm[None, :, 1]], 2)
    A = A * visible[..., None, None]  # [P,F,2,4]
    A = A / np.maximum(np.linalg.norm(A, axis=-1, keepdims=True), 1e-9)
    # reduced SVD: the full one also builds U [P, 2F, 2F] (52 GB for 20k tracks over 300 frames)
    _, _, vt = np.linalg.svd(A.reshape(P, 2 * F, 4).astype(np.float64), full_matrices=False)
    Xh = vt[:, -1]
    X = Xh[:, :3] / np.where(np.abs(Xh[:, 3:]) < 1e-12, 1e-12, Xh[:, 3:])
    cam = np.einsum("fij,pj->pfi", w2c[:, :3, :3], X) + w2c[None, :, :3, 3]
    z = cam[..., 2]
    proj = np.einsum("fij,pfj->pfi", K, cam)
    uv = proj[..., :2] / np.where(np.abs(proj[..., 2:]) < 1e-9, 1e-9, proj[..., 2:])
    err = np.linalg.norm(uv - xy, axis=-1)
    nvis = visible.sum(1)
    ok = (nvis >= 2) & np.all(~visible | ((z > 0) & (err < max_reproj)), axis=1)
    centres = -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])  # [F,3]
    rays = X[:, None] - centres[None]
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    spread = np.where(visible[..., None], rays, -np.inf).max(1) - np.where(visible[..., None], rays, np.inf).min(1)
    spread = np.where(np.isfinite(spread), spread, 0.0)
    angle = np.degrees(np.linalg.norm(spread, axis=-1))  # ~ ray angle spread (chord length, radians)
    ok &= angle >= min_angle_deg
    return X.astype(np.float32), ok


#: Tracks seen (as static) in at least this many frames are trusted as depth anchors as
#: they are; shorter ones only within the depth range the long ones establish
#: (:func:`anchors_from_tracks`). Two or three views leave one or three equations to reject
#: a point whose image motion is not parallax, and a moving point often passes: on
#: bedroom.mp4 97 % of the triangulated two-view tracks (83 % of three-view, 65 % of four-
#: and five-view) came out under 0.3x the scene's median depth -- down to 1/900 of it --
#: against 4 % of those seen six times or more (docs/benchmarks.md).
ANCHOR_LONG_VIEWS = 6
#: A short track's point may be no nearer than this fraction of the 5th percentile of the
#: long tracks' depths (their own near range, with some room for a nearer surface).
SHORT_TRACK_NEAR_FRACTION = 0.5


def anchors_from_tracks(tracks, K, w2c, dynamic=None, shape=None, min_anchors=20, max_reproj=2.0,
                        long_views=ANCHOR_LONG_VIEWS, near_fraction=SHORT_TRACK_NEAR_FRACTION):
    """Per-frame anchors ``[A,3]`` (u, v, depth) from triangulated static tracks.

    Tracks seen in ``long_views`` frames or more anchor as triangulated; a shorter track
    anchors only where its depth in every frame it is seen is at least ``near_fraction``
    times the 5th percentile of the long tracks' depths (no long tracks: no bound). Why: a
    short track on a moving object can pass the reprojection test with its motion read as
    parallax, which puts it just in front of the lens, and in inverse depth one such anchor
    outweighs hundreds of static ones around it (bedroom.mp4's last frames came out at
    1/9 of the room's depth). Short tracks are not dropped outright: on slowly moving
    objects they triangulate near their true depth, the only depth the weight-free prior
    has for them (generated large-motion scenes: masked held-out -0.6 dB without them).
    """
    xy, vis = tracks.xy.astype(np.float64), tracks.visible.copy()
    P, F = vis.shape
    if dynamic is not None:
        H, W = dynamic.shape[1:]
        u = np.clip(xy[..., 0].astype(np.int64), 0, W - 1); v = np.clip(xy[..., 1].astype(np.int64), 0, H - 1)
        vis &= dynamic[np.arange(F)[None], v, u] <= 0.5
    X, ok = triangulate_tracks(xy, vis, K.astype(np.float64), w2c.astype(np.float64), max_reproj)
    long_ = ok & (vis.sum(1) >= long_views)
    if long_.any() and not long_.all():
        z = np.einsum("fj,pj->pf", w2c[:, 2, :3], X.astype(np.float64)) + w2c[None, :, 2, 3]  # [P, F] camera z
        bound = near_fraction * float(np.percentile(z[long_[:, None] & vis], 5))
        nearest = np.where(vis, z, np.inf).min(1)
        ok &= long_ | (nearest >= bound)
    Xs = X[ok].astype(np.float64)
    out = []
    for f in range(F):
        sel = ok & vis[:, f]
        cam = Xs @ w2c[f, :3, :3].T + w2c[f, :3, 3]
        zf = (X[sel].astype(np.float64) @ w2c[f, :3, :3].T + w2c[f, :3, 3])[:, 2]
        a = np.concatenate([xy[sel, f], zf[:, None]], 1)
        if len(a) < min_anchors and len(Xs) and shape is not None:
            pr = cam @ K[f].T
            front = cam[:, 2] > 1e-6
            uv = pr[front, :2] / pr[front, 2:]
            H, W = shape
            inb = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
            a = np.concatenate([uv[inb], cam[front][inb, 2:3]], 1)
        out.append(a.astype(np.float32))
    return out


def _fgs(guide, src, lam, sigma):
    import cv2

    return cv2.ximgproc.fastGlobalSmootherFilter(guide, src, lam, sigma)


def push_pull(values, weights, empty=0.0, full=0.25):
    """Fill a sparse weighted map from its nearest data, coarse to fine (push-pull hole filling).

    ``values [h,w]`` holds weight-times-value sums, ``weights [h,w]`` the weights. The pyramid
    is built by weighted averaging (``cv2.pyrDown`` of both); going back up, each level keeps
    its own average where its weight density is at least ``full`` and blends in the upsampled
    coarser level where it is lower. A pixel therefore takes the average of the data around it
    at the finest scale that has any, with no pull toward a global value; ``empty`` only where
    the whole map has no weight. Returns the filled map ``[h,w]`` float32.
    """
    import cv2

    num, den = [values.astype(np.float32)], [weights.astype(np.float32)]
    while min(num[-1].shape) > 4:
        num.append(cv2.pyrDown(num[-1])); den.append(cv2.pyrDown(den[-1]))
    top = den[-1].sum()
    filled = np.full(num[-1].shape, num[-1].sum() / top if top > 0 else empty, np.float32)
    for level in range(len(num) - 1, -1, -1):
        n, d = num[level], den[level]
        up = cv2.resize(filled, (n.shape[1], n.shape[0]), interpolation=cv2.INTER_LINEAR)
        own = np.clip(d * 4.0 ** level / full, 0, 1)  # pyrDown averages: x 4**level = weight per pixel of this level
        filled = own * (n / np.maximum(d, 1e-12)) + (1 - own) * up
    return filled


def densify(frame, anchors, max_width=320, lam=2000.0, sigma_color=8.0, support_floor=0.002):
    """Edge-aware normalised convolution of sparse anchors -> (depth [H,W], confidence [H,W]).

    In inverse depth: ``FGS(1/d * c) / FGS(c)`` guided by the frame. Where the edge-aware
    support ``FGS(c)`` is tiny (regions walled off by edges, e.g. a checker square with no
    anchor) the value falls back to an edge-blind interpolation of the same anchors
    (:func:`push_pull`), so an isolated region takes its neighbours' depth.

    Why ``support_floor`` is small (a fraction of the 90th-percentile support): the floor is
    a prior pulled into every pixel with that weight. It used to be 0.02 toward the frame's
    median depth, which shrank every pixel's depth toward the median: on the generated small
    scenes the far wall came out 2-4 % too near and the near floor 2-3 % too far *at the
    anchors themselves* (anchors unbiased), background AbsRel 0.023 -> 0.011 without it
    (docs/benchmarks.md, "Depth prior: shrinkage toward the median").
    """
    import cv2

    H, W = frame.shape[:2]
    s = min(1.0, max_width / W)
    w, h = max(8, int(round(W * s))), max(8, int(round(H * s)))
    guide = cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA)
    u = np.clip((anchors[:, 0] * s).astype(np.int64), 0, w - 1)
    v = np.clip((anchors[:, 1] * s).astype(np.int64), 0, h - 1)
    inv = np.zeros((h, w), np.float32); cnt = np.zeros((h, w), np.float32)
    np.add.at(inv, (v, u), 1.0 / anchors[:, 2]); np.add.at(cnt, (v, u), 1.0)
    median_inv = float(np.median(1.0 / anchors[:, 2]))

    num = _fgs(guide, inv, lam, sigma_color); den = np.maximum(_fgs(guide, cnt, lam, sigma_color), 0)
    ref = float(np.percentile(den, 90)) + 1e-9
    eps = support_floor * ref
    fallback = push_pull(inv, cnt, median_inv)  # edge-blind: what the nearest anchors say
    dens = (num + eps * fallback) / (den + eps)
    dens = np.where(dens > 1e-9, dens, median_inv)
    conf = np.clip(den / ref, 0, 1)
    dep = cv2.resize((1.0 / dens).astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
    return dep, cv2.resize(conf.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)


def _ellipse(d):
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (max(3, int(d) | 1),) * 2)


def merge_moving_depth(first, static, dynamic, threshold=0.5, max_ratio=4.0, front=0.9):
    """Depth of the second (static-anchored) pass with the moving pixels of the first pass,
    bounded by occlusion order -> float32 [F,H,W].

    ``first``: the depth anchored on every triangulated track, moving ones included;
    ``static``: the same with anchors on moving pixels dropped; ``dynamic [F,H,W]``: the motion
    mask. A track on a slowly moving object often triangulates close to its true depth (the
    generated small-motion scenes: moving-pixel median error 7 % with it, 105 % without: the
    background's depth); one whose motion mimics parallax lands anywhere in front of the lens
    (bedroom.mp4: down to 1/900 of the room's depth). So moving pixels keep the first pass's value
    only inside what occlusion order allows: no farther than the static surface behind them
    (``static`` there) and no nearer than ``1 / max_ratio`` of it; where the first pass puts
    them at that surface or behind it, it has no depth of their own to give, and they go in
    front of it, to ``front`` times its depth. Static pixels take ``static`` -- the first
    pass's moving anchors no longer leak into the scene around them.

    Why ``front`` < 1: a camera that does not translate gives the weight-free depth as one
    constant sphere; moving and static Gaussians were seeded at the same depth and tied, the
    static ones, trained on every frame where the background shows, won, and a cup slid across
    cups.mp4's table rendered behind the table (docs/benchmarks.md, "Moving objects").
    Measured depths in front of the surface are kept as they are (moving every moving pixel
    to at most 0.9x cost the generated large-motion scenes' node paths).
    """
    first = np.asarray(first, np.float32); static = np.asarray(static, np.float32)
    moving = np.asarray(dynamic) >= threshold
    bounded = np.clip(first, static / float(max_ratio), static)
    bounded = np.where(first >= static, static * float(front), bounded)  # tie or behind: in front
    return np.where(moving & (first > 0) & np.isfinite(first), bounded, static).astype(np.float32)


def support_fill(depth, moving, q=5.0, gap=2, ring=5, min_px=20):
    """Cap each connected moving region at the depth of its nearest support -> depth [H,W].

    ``depth [H,W]``, ``moving [H,W]`` bool. Per 8-connected region of ``moving`` (at least
    ``min_px`` pixels): the ``q``-th percentile of ``depth`` over the non-moving pixels at
    ``gap`` .. ``gap + ring`` px from the region (a ring; near a region boundary ``gap`` skips
    the mask's smear); inside the region ``depth = min(depth, that value)``. A region without
    ring pixels is left as it is. Never increases the depth; pixels outside ``moving`` are
    returned unchanged. Vectorised: one connected-components pass, a grey dilation of the
    label image and a per-label percentile from one lexsort.
    """
    import cv2

    depth = np.asarray(depth, np.float32)
    m = np.asarray(moving, bool).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return depth.copy()
    labd = cv2.dilate(lab.astype(np.float32), _ellipse(2 * (gap + ring) + 1)).astype(np.int64)
    inner = cv2.dilate(m, _ellipse(2 * gap + 1)) > 0
    sel = (labd > 0) & ~inner & np.isfinite(depth) & (depth > 0)
    L, v = labd[sel], depth[sel]
    out = depth.copy()
    if len(L) == 0:
        return out
    o = np.lexsort((v, L))
    L, v = L[o], v[o]
    cnt = np.bincount(L, minlength=n)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    idx = np.clip(start + np.floor((cnt - 1) * float(q) / 100.0).astype(np.int64), 0, len(v) - 1)
    val = np.where(cnt > 0, v[idx], np.inf).astype(np.float32)
    val[0] = np.inf
    val[stats[:, cv2.CC_STAT_AREA] < min_px] = np.inf
    inr = lab > 0
    out[inr] = np.minimum(depth[inr], val[lab[inr]])
    return out


def robust_affine(pred, target, iters=10):
    """IRLS Huber fit ``target ~ s*pred + t``; returns (s, t)."""
    w = np.ones_like(pred)
    s, t = 1.0, 0.0
    for _ in range(iters):
        A = np.stack([pred * w, w], 1)
        s, t = np.linalg.lstsq(A, target * w, rcond=None)[0]
        r = np.abs(s * pred + t - target)
        c = 1.345 * max(1.4826 * np.median(r), 1e-9)
        w = np.sqrt(np.where(r <= c, 1.0, c / np.maximum(r, 1e-12)))
    return float(s), float(t)


def estimate_depth(frames, K, w2c, backend="sparse", model_path=None, anchors=None, dynamic=None, tracks=None,
                   max_width=320, min_anchors=20, reporter=None, moving_fill="surround", output=None,
                   predictions=None, settings=None):
    """Dense metric depth for every frame.

    Parameters
    ----------
    frames : uint8 [F,H,W,3]; K : [F,3,3]; w2c : [F,4,4]
    backend : 'sparse' | 'onnx'
    anchors : list of F arrays [A,3] (u, v, depth), optional (else built from ``tracks``)
    dynamic : [F,H,W] p_dyn, optional (anchors where > 0.5 are dropped)
    tracks : :class:`~engine.priors.tracks.Tracks`, used when ``anchors`` is None
    moving_fill : 'surround' (default) | 'support': sparse backend only, with ``dynamic``
        (see the module docstring and :func:`support_fill`)
    output : 'inverse' | 'depth' | None, onnx backend: what the model predicts (None: the
        sidecar's ``output``, else 'inverse')
    predictions : ``(pred [F,H,W], kind)`` from :func:`model_predictions`, onnx backend: align
        these instead of running the model again (the second depth pass of compute_priors)
    settings : dict or None, onnx backend: sidecar keys laid over the model's sidecar file
        (:func:`engine.priors.onnx_util.model_settings`)

    Returns
    -------
    depth : float32 [F,H,W]
    confidence : float32 [F,H,W] in [0,1]
    """
    frames = np.asarray(frames)
    F, H, W, _ = frames.shape
    K = np.asarray(K, np.float64); w2c = np.asarray(w2c, np.float64)
    if anchors is None:
        if tracks is None:
            raise InputError("depth needs anchors or tracks.", fix="Compute tracks first (compute_priors does).")
        anchors = anchors_from_tracks(tracks, K, w2c, dynamic, (H, W), min_anchors)
    anchors = [np.zeros((0, 3), np.float32) if a is None else np.asarray(a, np.float32) for a in anchors]
    if dynamic is not None:
        anchors = [a[dynamic[f, np.clip(a[:, 1].astype(int), 0, H - 1), np.clip(a[:, 0].astype(int), 0, W - 1)] <= 0.5]
                   for f, a in enumerate(anchors)]
    anchors = [a[np.isfinite(a).all(1) & (a[:, 2] > 0)] for a in anchors]
    alld = np.concatenate([a[:, 2] for a in anchors]) if anchors else np.zeros(0)
    median = float(np.median(alld)) if len(alld) else 1.0
    depth = np.empty((F, H, W), np.float32); conf = np.zeros((F, H, W), np.float32)
    if moving_fill not in ("surround", "support"):
        raise InputError(f"unknown moving_fill {moving_fill!r}.", fix="Use 'surround' or 'support'.")
    if backend == "sparse":
        scale = max(1.0, W / 320.0)  # ring sizes are in px of a <= 320 px wide frame
        for f in range(F):
            if len(anchors[f]) == 0:
                depth[f] = median
            else:
                depth[f], conf[f] = densify(frames[f], anchors[f], max_width)
            if moving_fill == "support" and dynamic is not None:
                depth[f] = support_fill(depth[f], dynamic[f] > 0.5, gap=int(round(2 * scale)),
                                        ring=int(round(5 * scale)), min_px=int(round(20 * scale * scale)))
            if reporter is not None:
                reporter.progress("depth", f + 1, F)
        return depth, conf
    if backend != "onnx":
        raise InputError(f"unknown depth backend {backend!r}.", fix="Use 'sparse' or 'onnx'.")
    if predictions is None:
        predictions = model_predictions(frames, model_path, max_width, output, reporter, settings)
    elif reporter is not None:
        reporter.progress("depth", F, F)
    return _align_predictions(*predictions, anchors, median)


def model_predictions(frames, model_path, max_width=320, output=None, reporter=None, settings=None):
    """Run an ONNX depth model on every frame -> ``(pred float32 [F,H,W], kind)``: the raw output
    resized to the frames, and ``kind`` 'inverse' (larger = nearer) or 'depth' (larger = farther)
    from ``output`` or the model's settings (its sidecar, ``settings`` laid over it)."""
    import cv2

    F, H, W, _ = frames.shape
    sess = onnx_util.load_session(model_path)
    side = onnx_util.model_settings(model_path, settings)
    name, layout, size, fixed = onnx_util.image_input_spec(sess, side, (384, 384))
    if "input_size" not in side and onnx_util.has_dynamic_hw(sess, layout):
        size = onnx_util.dynamic_input_size(H, W, side.get("input_width", max_width), side.get("size_multiple", 32))
    kind = output or side.get("output", "inverse")
    if kind not in ("inverse", "depth"):
        raise InputError(f"unknown depth model output {kind!r}.", model_path,
                         "Use 'inverse' (larger = nearer) or 'depth' (larger = farther).")
    pred = np.empty((F, H, W), np.float32)
    for f in range(F):
        x = onnx_util.prepare_images(frames[f:f + 1], size, layout, side.get("mean", onnx_util.IMAGENET_MEAN),
                                     side.get("std", onnx_util.IMAGENET_STD))
        out = np.asarray(sess.run(None, {name: x})[0], np.float32).reshape(size)
        pred[f] = cv2.resize(out, (W, H), interpolation=cv2.INTER_LINEAR)
        if reporter is not None:
            reporter.progress("depth", f + 1, F)
    return pred, kind


def at_anchors(image: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """``image [H, W]`` at the pixels of ``anchors [A, 3]`` (u, v, depth; nearest, clamped) -> ``[A]``."""
    h, w = image.shape
    return image[np.clip(anchors[:, 1].astype(int), 0, h - 1), np.clip(anchors[:, 0].astype(int), 0, w - 1)]


def fit_alignment(pred_at: np.ndarray, depth_at: np.ndarray, kind: str) -> tuple[float, float]:
    """Scale and shift ``(s, t)`` of a model's output at some anchors ``pred_at [A]`` onto their
    depths ``depth_at [A]``, robust affine in the model's ``kind`` of value ('inverse': fitted to
    1 / depth)."""
    target = 1.0 / depth_at if kind == "inverse" else depth_at
    return robust_affine(np.asarray(pred_at, np.float64), np.asarray(target, np.float64))


def aligned_depth(pred: np.ndarray, s: float, t: float, kind: str) -> np.ndarray:
    """Depth from a model's output ``pred`` and its alignment ``(s, t)`` (:func:`fit_alignment`)."""
    val = s * pred + t
    return 1.0 / np.maximum(val, 1e-6) if kind == "inverse" else val


def _align_predictions(pred, kind, anchors, median):
    """Each frame's model output ``pred [F,H,W]`` fitted to its anchors (robust affine, in the
    model's ``kind`` of value) -> (depth [F,H,W], confidence [F,H,W])."""
    F, H, W = pred.shape
    depth = np.empty((F, H, W), np.float32); conf = np.zeros((F, H, W), np.float32)
    for f in range(F):
        a = anchors[f]
        if len(a) >= 3:
            s, t = fit_alignment(at_anchors(pred[f], a), a[:, 2], kind)
            c = 0.9
        else:
            ref = 1.0 / median if kind == "inverse" else median
            s, t = ref / max(float(np.median(pred[f])), 1e-9), 0.0
            c = 0.2
        depth[f] = np.clip(aligned_depth(pred[f], s, t, kind), 1e-3 * median, 1e3 * median)
        conf[f] = c
    return depth, conf
