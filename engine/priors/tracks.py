"""Long 2D point tracks by chained dense optical flow.

``flow`` backend (weight-free): frames are converted to grey and downscaled to at most
``max_width`` px, or, when narrower than ``min_width``, upscaled by the smallest integer
factor that reaches it (DIS matches 8-px patches at its finest scale, which straddle the
boundary of a small moving object in a 240-px frame and drag its points along with the
background; at 2× the median track error on the moving objects of the small synthetic
scene drops from 4.3 to 1.5 px); DIS flow is computed forward (f->f+1) and backward (f+1->f). Each live
point is advanced by the bilinearly sampled forward flow; it is dropped (and stays
invisible for the rest of the clip) when the forward-backward error
``|fwd(p) + bwd(p + fwd(p))|`` exceeds ``fb_thresh + fb_rel*|fwd|`` (occlusion or bad
match) or when it leaves the image. After every step, cells of a regular grid with no live
point are re-seeded (only where the image has texture), so the whole clip is covered and
tracks start on later frames too (``query_frame``). Coordinates are continuous pixel
coordinates of the original frames.

The flow comes from a :class:`~engine.priors.flow.FlowSource` (``source``; default DIS as
above, or a learned RAFT-contract flow, fused per pixel with DIS, shared with the motion mask). Options, all measured
on the generated scenes (``python -m engine.bench priors``, docs/benchmarks.md) and off by
default because they did not pay off there: ``dense_moving`` re-seeds at half the grid cell
where the flow departs from a robust homography (about 3x the tracks on moving parts, better
moving-part coverage, but the extra short tracks triangulate as static anchors and worsen
the depth and the motion mask); ``bridge_gaps`` looks for a point that failed the one-frame
check in direct gap-2 / gap-4 flows (longer survival, but more wrong re-finds on moving
parts); ``retry`` re-tries a failed step with a second flow source. :func:`compute_priors`
gives the tracker a fused fine-scale DIS source by default (``FlowSource(fuse_fine=True)``,
``PriorConfig.flow_fine``): it follows small fast objects (moving-part coverage 0.33 -> 0.40
and 0.06 -> 0.10 on the generated small / large-motion scenes) at ~4x the flow time.

``onnx`` backend: a model with inputs ``frames`` float32 [F,3,H,W] (RGB in [0,1]) and
``queries`` float32 [P,3] (frame index, x, y in pixels of that input), outputs
``xy`` [P,F,2] and ``visible`` [P,F] (logits; > 0 visible). Queries are a grid on frame 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from . import flow as _flow
from . import onnx_util


@dataclass
class Tracks:
    """``xy [P,F,2]`` float32 pixels, ``visible [P,F]`` bool, ``confidence [P,F]`` float32, ``query_frame [P]`` int;
    ``depth [P,F]`` float32 or None: a camera depth the track carries itself (NaN where the depth map
    decides; :mod:`engine.priors.hinge_tracks`), used wherever tracks are lifted: the node paths
    (``lift_tracks``) and the track term (``TrainingData.tracks_depth``, ``Objective.prepare_tracks``);
    ``translation_only [P]`` bool or None: tracks that follow their object's translation alone
    (:mod:`engine.priors.blob_tracks`), which tell nothing of how it turns, so the node rotations
    are fitted without them (``engine.nodes.initialise_nodes``)."""

    xy: np.ndarray
    visible: np.ndarray
    confidence: np.ndarray
    query_frame: np.ndarray
    depth: np.ndarray | None = None
    translation_only: np.ndarray | None = None


def tracks_from_paths(paths, width: int, height: int, min_frames: int, translation_only: bool = False) -> Tracks | None:
    """Tracks from seeded paths (:mod:`engine.priors.hinge_tracks`, :mod:`engine.priors.blob_tracks`).

    ``paths``: ``(xy [P, F, 2] px, seen [P, F] or [F] bool, depth [F] or [P, F] camera depth, seed
    frame)`` per seed frame; a sample is visible where seen, finite and inside the ``width`` x ``height``
    image, and carries the frame's depth; tracks visible in fewer than ``min_frames`` frames are
    dropped. Returns :class:`Tracks` (``query_frame`` the seed frame, ``translation_only`` set
    when asked) or None when none is left.
    """
    xy_all, vis_all, z_all, q_all = [], [], [], []
    for xy, seen, depth, seed in paths:  # seed frames (a few per object)
        vis = np.broadcast_to(seen, xy.shape[:2]) & np.isfinite(xy).all(-1)
        vis &= (xy[..., 0] >= 0) & (xy[..., 0] < width) & (xy[..., 1] >= 0) & (xy[..., 1] < height)
        xy_all.append(np.where(vis[..., None], xy, 0.0).astype(np.float32))
        vis_all.append(vis)
        z_all.append(np.where(vis, np.broadcast_to(depth, vis.shape), np.nan).astype(np.float32))
        q_all.append(np.full(len(xy), seed, np.int64))
    if not xy_all:
        return None
    xy, vis, z, q = (np.concatenate(a) for a in (xy_all, vis_all, z_all, q_all))
    long = vis.sum(1) >= min_frames
    if not long.any():
        return None
    flag = np.ones(int(long.sum()), bool) if translation_only else None
    return Tracks(xy[long], vis[long], vis[long].astype(np.float32), q[long], depth=z[long], translation_only=flag)


def concat_tracks(first: Tracks, more: Tracks | None) -> Tracks:
    """``first`` followed by the rows of ``more`` (same frames); a ``depth`` that only one of them
    has is NaN for the other's rows, a ``translation_only`` False."""
    if more is None or not len(more.xy):
        return first
    depth = None
    if first.depth is not None or more.depth is not None:
        nan = lambda t: np.full(t.visible.shape, np.nan, np.float32)  # noqa: E731
        depth = np.concatenate([nan(t) if t.depth is None else t.depth.astype(np.float32) for t in (first, more)])
    translation_only = None
    if first.translation_only is not None or more.translation_only is not None:
        flag = lambda t: np.zeros(len(t.xy), bool) if t.translation_only is None else t.translation_only.astype(bool)  # noqa: E731
        translation_only = np.concatenate([flag(first), flag(more)])
    cat = lambda name: np.concatenate([getattr(first, name), getattr(more, name).astype(getattr(first, name).dtype)])  # noqa: E731
    return Tracks(cat("xy"), cat("visible"), cat("confidence"), cat("query_frame"), depth, translation_only)


def _seed(occupied_xy, h, w, cell, tex, margin=2.0):
    """Centres of grid cells (working res) with no point in ``occupied_xy`` and texture."""
    gh, gw = max(1, int(h // cell)), max(1, int(w // cell))
    occ = np.zeros((gh, gw), bool)
    if len(occupied_xy):
        ci = np.clip((occupied_xy[:, 1] / cell).astype(np.int64), 0, gh - 1)
        cj = np.clip((occupied_xy[:, 0] / cell).astype(np.int64), 0, gw - 1)
        occ[ci, cj] = True
    ii, jj = np.nonzero(~occ)
    xy = np.stack([(jj + 0.5) * cell, (ii + 0.5) * cell], -1).astype(np.float32)
    ok = (xy[:, 0] > margin) & (xy[:, 0] < w - margin) & (xy[:, 1] > margin) & (xy[:, 1] < h - margin)
    xy = xy[ok]
    if len(xy):
        t = _flow.bilinear(tex[..., None], xy)[:, 0]
        xy = xy[t > 1e-3]
    return xy


def _texture(g):
    """Local gradient energy [h,w] of a grey frame (seeds only where the image has texture)."""
    import cv2

    g = g.astype(np.float32) / 255.0
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
    return cv2.boxFilter(gx * gx + gy * gy, -1, (5, 5))


def _moving_region(fwd, step=4, min_px=1.0, k=3.0):
    """Bool [h,w]: pixels whose flow departs from the frame's dominant motion.

    A homography fitted robustly (RANSAC) to a strided sample of the flow stands for the
    camera-induced motion; a pixel is *moving* where its residual exceeds
    ``max(min_px, median + k·1.4826·MAD)``. Coarse (parallax also shows up), used only to
    seed tracks more densely there.
    """
    import cv2

    h, w = fwd.shape[:2]
    ys, xs = np.mgrid[step // 2:h:step, step // 2:w:step]
    src = np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2).astype(np.float32)
    dst = src + fwd[ys, xs].reshape(-1, 2)
    if len(src) < 8:
        return np.zeros((h, w), bool)
    Hm, _ = cv2.findHomography(src, dst, cv2.RANSAC, 1.0)
    if Hm is None:
        return np.zeros((h, w), bool)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    pts = np.stack([xx + 0.5, yy + 0.5], -1).reshape(-1, 1, 2)
    pred = cv2.perspectiveTransform(pts, Hm).reshape(h, w, 2)
    r = np.linalg.norm(pts.reshape(h, w, 2) + fwd - pred, axis=-1)
    med = float(np.median(r)); mad = 1.4826 * float(np.median(np.abs(r - med)))
    return r > max(min_px, med + k * mad)


def _fb(source, f, g, p):
    """Advance ``p [P,2]`` by flow ``f -> g``: ``(q [P,2], fb error [P], |d| [P])``."""
    d = _flow.bilinear(source(f, g), p)
    q = p + d
    return q, np.linalg.norm(d + _flow.bilinear(source(g, f), q), axis=1), np.linalg.norm(d, axis=1)


def flow_tracks(frames, num_points=2000, max_width=480, fb_thresh=1.0, fb_rel=0.05, preset="medium",
                reporter=None, min_width=400, source=None, bridge_gaps=(), bridge_min=4, dense_moving=False,
                retry=None):
    """Chained-flow tracks (see module docstring). Returns :class:`Tracks`.

    ``source`` : :class:`~engine.priors.flow.FlowSource` (default: DIS at ``max_width`` /
    ``min_width``). ``bridge_gaps`` : direct multi-frame flows tried, in order, for tracks that
    fail the one-frame forward-backward check (only when at least ``bridge_min`` fail in that
    step). ``dense_moving`` : re-seed at half the grid cell inside moving regions. ``retry`` : a
    second :class:`~engine.priors.flow.FlowSource` of the same working size; a point that fails
    the check with ``source`` is advanced with it instead when it passes there.
    """
    F, H, W, _ = frames.shape
    if source is None:
        source = _flow.FlowSource(frames, "dis", None, max_width, min_width, preset)
    gray, s = source.gray, source.scale
    h, w = gray.shape[1:]
    cell = max(2.0, float(np.sqrt(h * w / max(int(num_points), 1))))

    def inside(q):
        return (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)

    pos = _seed(np.zeros((0, 2), np.float32), h, w, cell, _texture(gray[0]))
    hist_xy, hist_vis, hist_conf = [], [], []  # per frame arrays over all tracks so far
    qf = np.zeros(len(pos), np.int64)
    alive = np.ones(len(pos), bool)
    cur = pos.copy()
    conf = np.ones(len(pos), np.float32)
    land = {}  # frame -> (track indices, positions, confidences) of bridged tracks landing there
    hist_xy.append(cur.copy()); hist_vis.append(alive.copy()); hist_conf.append(conf.copy())
    for f in range(F - 1):
        idx = np.nonzero(alive)[0]
        p = cur[idx]
        q, err, mag = _fb(source, f, f + 1, p)
        ok = inside(q) & (err <= fb_thresh + fb_rel * mag)
        if retry is not None and (~ok).any():
            bad = np.flatnonzero(~ok)
            q2, e2, m2 = _fb(retry, f, f + 1, p[bad])
            ok2 = inside(q2) & (e2 <= fb_thresh + fb_rel * m2)
            q[bad[ok2]], err[bad[ok2]], ok[bad[ok2]] = q2[ok2], e2[ok2], True
        cur[idx] = q
        alive[idx[~ok]] = False
        conf[idx] = np.where(ok, np.exp(-err / max(fb_thresh, 1e-6)), 0.0)
        # bridge: a point lost between f and f+1 (blur, brief occlusion) may be found at f+k
        todo, pt = idx[~ok], p[~ok]
        for k in bridge_gaps if len(todo) >= bridge_min else ():
            if f + k >= F or not len(todo):
                break
            qk, ek, mk = _fb(source, f, f + k, pt)
            good = inside(qk) & (ek <= fb_thresh + fb_rel * mk)
            if good.any():
                prev = land.get(f + k)
                new = (todo[good], qk[good], np.exp(-ek[good] / max(fb_thresh, 1e-6)).astype(np.float32))
                land[f + k] = new if prev is None else tuple(np.concatenate([a, b]) for a, b in zip(prev, new))
            todo, pt = todo[~good], pt[~good]
        conf[~alive] = 0.0
        if f + 1 in land:
            li, lq, lc = land.pop(f + 1)
            li, first = np.unique(li, return_index=True)
            keep = ~alive[li]
            cur[li[keep]], conf[li[keep]], alive[li[keep]] = lq[first][keep], lc[first][keep], True
        tex = _texture(gray[f + 1])
        new = _seed(cur[alive], h, w, cell, tex)
        if dense_moving:
            mov = _moving_region(source(f, f + 1))
            fine = _seed(np.concatenate([cur[alive], new]), h, w, cell / 2, tex)
            if len(fine):
                # moving region of frame f, looked up where the fine seed came from (one-step back-warp)
                back = fine + _flow.bilinear(source(f + 1, f), fine)
                m = _flow.bilinear(mov[..., None].astype(np.float32), back)[:, 0] > 0.5
                new = np.concatenate([new, fine[m]])
        if len(new):
            cur = np.concatenate([cur, new]); alive = np.concatenate([alive, np.ones(len(new), bool)])
            conf = np.concatenate([conf, np.ones(len(new), np.float32)])
            qf = np.concatenate([qf, np.full(len(new), f + 1, np.int64)])
        hist_xy.append(cur.copy()); hist_vis.append(alive.copy()); hist_conf.append(conf.copy())
        if reporter is not None:
            reporter.progress("tracks", f + 1, F - 1, points=int(alive.sum()))
    return _assemble(hist_xy, hist_vis, hist_conf, qf, F, s)


def _assemble(hist_xy, hist_vis, hist_conf, qf, F, s):
    """Per-frame histories -> :class:`Tracks` in frame pixels (``s`` = working px per frame px)."""
    P = len(hist_xy[-1])
    xy = np.zeros((P, F, 2), np.float32)
    vis = np.zeros((P, F), bool)
    cf = np.zeros((P, F), np.float32)
    for f in range(F):
        n = len(hist_xy[f])
        xy[:n, f] = hist_xy[f]; vis[:n, f] = hist_vis[f]; cf[:n, f] = hist_conf[f]
    # before a track starts / after it is lost: hold the nearest known position (invisible)
    first = qf
    fidx = np.arange(F)
    before = fidx[None] < first[:, None]
    xy[before] = np.repeat(xy[np.arange(P), first][:, None], F, 1)[before]
    last_vis = np.where(vis.any(1), F - 1 - np.argmax(vis[:, ::-1], axis=1), first)
    after = fidx[None] > last_vis[:, None]
    xy[after] = np.repeat(xy[np.arange(P), last_vis][:, None], F, 1)[after]
    return Tracks((xy / s).astype(np.float32), vis, cf * vis, qf)


def onnx_tracks(frames, model_path, num_points=2000):
    """Tracks from an ONNX tracker with the I/O contract in the module docstring."""
    sess = onnx_util.load_session(model_path)
    F, H, W, _ = frames.shape
    names = [i.name for i in sess.get_inputs()]
    if set(names) != {"frames", "queries"}:
        raise InputError(f"tracker inputs must be 'frames' and 'queries', got {names}.", model_path)
    cell = max(2.0, float(np.sqrt(H * W / num_points)))
    xs, ys = np.arange(cell / 2, W, cell), np.arange(cell / 2, H, cell)
    g = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    queries = np.concatenate([np.zeros((len(g), 1)), g], 1).astype(np.float32)
    inp = (frames.astype(np.float32) / 255.0).transpose(0, 3, 1, 2).copy()
    xy, vis = sess.run(None, {"frames": inp, "queries": queries})[:2]
    xy, vis = np.asarray(xy, np.float32), np.asarray(vis, np.float32)
    if xy.shape != (len(g), F, 2) or vis.shape != (len(g), F):
        raise InputError(f"tracker outputs {xy.shape}, {vis.shape}; expected [P,F,2], [P,F].", model_path)
    conf = (1.0 / (1.0 + np.exp(-vis))).astype(np.float32)
    return Tracks(xy, vis > 0, conf, np.zeros(len(g), np.int64))


def track_points(frames, num_points=2000, backend="flow", model_path=None, max_width=480, fb_thresh=1.0,
                 fb_rel=0.05, preset="medium", reporter=None, min_width=400, source=None, **kw):
    """Long 2D tracks over the whole clip.

    Parameters
    ----------
    frames : uint8 [F,H,W,3]
    num_points : target number of simultaneously tracked points (grid density)
    backend : 'flow' | 'onnx'
    max_width : flow working width (px); wider frames are downscaled
    min_width : narrower frames are upscaled by an integer factor to at least this width
    fb_thresh, fb_rel : forward-backward threshold in working px, absolute + relative to |flow|
    source : :class:`~engine.priors.flow.FlowSource`, optional (``flow`` backend; default DIS)
    **kw : bridging / seeding options of :func:`flow_tracks`

    Returns
    -------
    Tracks
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.dtype != np.uint8:
        raise InputError(f"frames must be uint8 [F,H,W,3], got {frames.dtype} {frames.shape}.")
    if backend == "flow":
        return flow_tracks(frames, num_points, max_width, fb_thresh, fb_rel, preset, reporter, min_width, source, **kw)
    if backend == "onnx":
        return onnx_tracks(frames, model_path, num_points)
    raise InputError(f"unknown tracks backend {backend!r}.", fix="Use 'flow' or 'onnx'.")
