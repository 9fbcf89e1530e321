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
    """``xy [P,F,2]`` float32 pixels, ``visible [P,F]`` bool, ``confidence [P,F]`` float32, ``query_frame [P]`` int."""

    xy: np.ndarray
    visible: np.ndarray
    confidence: np.ndarray
    query_frame: np.ndarray


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


def _working_gray(frames, max_width, min_width):
    """Grey frames at the flow working width and their scale (working px per frame px)."""
    import cv2

    gray, s = _flow.to_gray_small(frames, max_width)
    up = int(np.ceil(min_width / gray.shape[2])) if min_width and gray.shape[2] < min_width else 1
    if up > 1:
        gray = np.stack([cv2.resize(g, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC) for g in gray])
        s = s * up
    return gray, s


def flow_tracks(frames, num_points=2000, max_width=480, fb_thresh=1.0, fb_rel=0.05, preset="medium",
                reporter=None, min_width=400):
    """Chained-DIS tracks (see module docstring). Returns :class:`Tracks`."""
    import cv2

    F, H, W, _ = frames.shape
    gray, s = _working_gray(frames, max_width, min_width)
    h, w = gray.shape[1:]
    cell = max(2.0, float(np.sqrt(h * w / max(int(num_points), 1))))

    def texture(g):
        g = g.astype(np.float32) / 255.0
        gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
        return cv2.boxFilter(gx * gx + gy * gy, -1, (5, 5))

    pos = _seed(np.zeros((0, 2), np.float32), h, w, cell, texture(gray[0]))
    hist_xy, hist_vis, hist_conf = [], [], []  # per frame arrays over all tracks so far
    qf = np.zeros(len(pos), np.int64)
    alive = np.ones(len(pos), bool)
    cur = pos.copy()
    conf = np.ones(len(pos), np.float32)
    hist_xy.append(cur.copy()); hist_vis.append(alive.copy()); hist_conf.append(conf.copy())
    for f in range(F - 1):
        fwd = _flow.dis_flow(gray[f], gray[f + 1], preset)
        bwd = _flow.dis_flow(gray[f + 1], gray[f], preset)
        idx = np.nonzero(alive)[0]
        p = cur[idx]
        d = _flow.bilinear(fwd, p)
        q = p + d
        err = np.linalg.norm(d + _flow.bilinear(bwd, q), axis=1)
        thr = fb_thresh + fb_rel * np.linalg.norm(d, axis=1)
        inside = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
        ok = inside & (err <= thr)
        cur[idx] = q
        alive[idx[~ok]] = False
        conf[idx] = np.where(ok, np.exp(-err / max(fb_thresh, 1e-6)), 0.0)
        conf[~alive] = 0.0
        new = _seed(cur[alive], h, w, cell, texture(gray[f + 1]))
        if len(new):
            cur = np.concatenate([cur, new]); alive = np.concatenate([alive, np.ones(len(new), bool)])
            conf = np.concatenate([conf, np.ones(len(new), np.float32)])
            qf = np.concatenate([qf, np.full(len(new), f + 1, np.int64)])
        hist_xy.append(cur.copy()); hist_vis.append(alive.copy()); hist_conf.append(conf.copy())
        if reporter is not None:
            reporter.progress("tracks", f + 1, F - 1, points=int(alive.sum()))
    P = len(cur)
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
                 fb_rel=0.05, preset="medium", reporter=None, min_width=400):
    """Long 2D tracks over the whole clip.

    Parameters
    ----------
    frames : uint8 [F,H,W,3]
    num_points : target number of simultaneously tracked points (grid density)
    backend : 'flow' | 'onnx'
    max_width : flow working width (px); wider frames are downscaled
    min_width : narrower frames are upscaled by an integer factor to at least this width
    fb_thresh, fb_rel : forward-backward threshold in working px, absolute + relative to |flow|

    Returns
    -------
    Tracks
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.dtype != np.uint8:
        raise InputError(f"frames must be uint8 [F,H,W,3], got {frames.dtype} {frames.shape}.")
    if backend == "flow":
        return flow_tracks(frames, num_points, max_width, fb_thresh, fb_rel, preset, reporter, min_width)
    if backend == "onnx":
        return onnx_tracks(frames, model_path, num_points)
    raise InputError(f"unknown tracks backend {backend!r}.", fix="Use 'flow' or 'onnx'.")
