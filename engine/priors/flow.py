"""Dense optical flow: DIS (weight-free) or RAFT-style ONNX, memoised per frame pair.

:class:`FlowSource` is the one place a prior asks for flow. It owns the clip's frames at a
working size and returns ``[h,w,2]`` float32 flows (dx, dy in working px; pixel ``(i, j)``
has its centre at ``(j+.5, i+.5)``) for any frame pair, computed once and kept in memory, so
the tracker and the motion mask can share the (expensive) learned flows.

``dis`` backend: ``cv2.DISOpticalFlow`` on grey frames (``preset`` medium).

``onnx`` backend (RAFT contract): inputs ``image1``, ``image2`` float32 ``[1,3,H,W]`` RGB in
0..255 (normalisation is inside the graph), ``H`` and ``W`` multiples of 8 (the frames are
edge-padded at the bottom/right and the flow cropped back); first output ``flow``
``[1,2,H,W]`` (x, y displacement image1 -> image2). RAFT-small (BSD-3-Clause) ships in
``engine/priors/models/`` (:func:`shipped_flow_model`).

:class:`FusedFlowSource` (what :func:`engine.priors.compute_priors` uses with a learned flow
unless ``PriorConfig.flow_fuse_dis`` is off): per pixel the learned flow or DIS, whichever has
the lower photometric residual.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError

MODELS_DIR = Path(__file__).resolve().parent / "models"
SHIPPED_FLOW = "raft_small_it6.onnx"


def shipped_flow_model():
    """Path of the RAFT-small model shipped with the engine, or ``None`` when absent/unusable.

    ``None`` also when onnxruntime cannot be imported: the default then falls back to DIS.
    """
    p = MODELS_DIR / SHIPPED_FLOW
    if not p.is_file():
        return None
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return None
    return str(p)


def resolve_flow_backend(backend, model_path):
    """``(backend, model_path)`` with ``'auto'`` resolved: the shipped RAFT when usable, else DIS."""
    if backend == "auto":
        if model_path:
            return "onnx", str(model_path)
        shipped = shipped_flow_model()
        return ("onnx", shipped) if shipped else ("dis", None)
    if backend not in ("dis", "onnx"):
        raise InputError(f"unknown flow backend {backend!r}.", fix="Use 'auto', 'dis' or 'onnx'.")
    if backend == "onnx" and not model_path:
        model_path = shipped_flow_model()
        if model_path is None:
            raise InputError("flow backend 'onnx' needs a model.", fix="Pass --flow-model PATH (a RAFT ONNX export).")
    return backend, (str(model_path) if model_path else None)


def working_size(H, W, max_width, min_width=0):
    """``(h, w, scale)``: frames narrower than ``max_width`` keep their size, wider ones are
    downscaled to it; narrower than ``min_width`` they are upscaled by the smallest integer
    factor that reaches it (see :mod:`engine.priors.tracks` for why)."""
    s = min(1.0, float(max_width) / W)
    w, h = max(8, int(round(W * s))), max(8, int(round(H * s)))
    up = int(np.ceil(min_width / w)) if min_width and w < min_width else 1
    return h * up, w * up, (w * up) / W


def to_gray_small(frames, max_width=480):
    """uint8 RGB [F,H,W,3] -> (uint8 gray [F,h,w], scale = w/W) with w <= max_width."""
    import cv2

    F, H, W, _ = frames.shape
    s = min(1.0, float(max_width) / W)
    w, h = max(8, int(round(W * s))), max(8, int(round(H * s)))
    gray = np.stack([cv2.resize(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), (w, h), interpolation=cv2.INTER_AREA)
                     if (w, h) != (W, H) else cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames])
    return gray, w / W


def dis_flow(a, b, preset="medium"):
    """Flow [h,w,2] (dx, dy) from gray ``a`` to gray ``b`` (pixel (i,j) centre at (j+.5, i+.5))."""
    import cv2

    p = {"fast": cv2.DISOPTICAL_FLOW_PRESET_FAST, "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
         "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}[preset]
    dis = cv2.DISOpticalFlow_create(p)
    return dis.calc(a, b, None)


def pull_back(img, flow):
    """``img`` [h,w(,C)] sampled at ``p + flow(p)`` for every pixel ``p`` of ``flow [h,w,2]``
    (bilinear, edges replicated): frame ``g`` brought onto frame ``f`` by the flow ``f -> g``."""
    import cv2

    h, w = flow.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(img, xs + flow[..., 0], ys + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def fb_error(a, b):
    """Forward-backward error ``|a(p) + b(p + a(p))|`` [h,w] of flows ``a`` (f->g) and ``b`` (g->f)."""
    e = a + pull_back(b, a)
    return np.hypot(e[..., 0], e[..., 1])


def dis_fused(a, b, preset="medium"):
    """DIS flows both ways between grey ``a`` and ``b``, fused per pixel -> (fwd, bwd) [h,w,2].

    The ``preset`` flow (finest scale 1: patches at half resolution) is exact on the static
    scene but drags small fast objects along with their surroundings; the same preset at
    finest scale 0 follows them (1-frame error on moving parts of the large-motion generated
    scene 1.56 -> 0.50 px median) but is noisier on the background (0.09 -> 0.16 px). Each
    pixel takes the flow whose forward-backward error (5x5 mean) is lower.
    """
    import cv2

    def both(fs):
        out = []
        for x, y in ((a, b), (b, a)):
            d = cv2.DISOpticalFlow_create({"fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                                           "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
                                           "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}[preset])
            if fs is not None:
                d.setFinestScale(fs)
            out.append(d.calc(x, y, None))
        return out

    (cf, cb), (ff, fb) = both(None), both(0)
    pick_f = cv2.blur(fb_error(ff, fb), (5, 5)) < cv2.blur(fb_error(cf, cb), (5, 5))
    pick_b = cv2.blur(fb_error(fb, ff), (5, 5)) < cv2.blur(fb_error(cb, cf), (5, 5))
    return np.where(pick_f[..., None], ff, cf), np.where(pick_b[..., None], fb, cb)


def raft_session(model_path):
    """ONNX session of a RAFT-contract model; checks the input names (one clear error otherwise)."""
    from . import onnx_util

    sess = onnx_util.load_session(model_path)
    names = [i.name for i in sess.get_inputs()]
    if names[:2] != ["image1", "image2"]:
        raise InputError(f"flow model inputs must be 'image1', 'image2', got {names}.", model_path,
                         "Export RAFT with input names image1/image2 ([1,3,H,W] RGB 0..255).")
    return sess


def raft_flow(sess, a, b):
    """Flow [h,w,2] from uint8 RGB ``a [h,w,3]`` to ``b`` with a RAFT-contract session (pads to /8)."""
    h, w = a.shape[:2]
    ph, pw = (-h) % 8, (-w) % 8

    def prep(x):
        x = np.pad(x, ((0, ph), (0, pw), (0, 0)), mode="edge") if (ph or pw) else x
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None], dtype=np.float32)

    out = np.asarray(sess.run(None, {"image1": prep(a), "image2": prep(b)})[0], np.float32)
    if out.ndim != 4 or out.shape[:2] != (1, 2) or out.shape[2] < h or out.shape[3] < w:
        raise InputError(f"flow model output has shape {out.shape}; expected [1,2,H,W].")
    return np.ascontiguousarray(out[0, :, :h, :w].transpose(1, 2, 0))


class FlowSource:
    """Memoised pairwise flows of one clip at a working size.

    Parameters
    ----------
    frames : uint8 [F,H,W,3] RGB
    backend : 'dis' | 'onnx'
    model_path : RAFT-contract ONNX file (``onnx``)
    max_width, min_width : working size (:func:`working_size`)
    preset : DIS preset
    fuse_fine : DIS only: per-pixel fusion with the finest-scale flow (:func:`dis_fused`)

    Attributes
    ----------
    size : (h, w) working size; ``scale`` = w / W; ``gray`` uint8 [F,h,w]
    """

    def __init__(self, frames, backend="dis", model_path=None, max_width=480, min_width=0, preset="medium",
                 fuse_fine=False):
        import cv2

        frames = np.asarray(frames)
        F, H, W, _ = frames.shape
        h, w, self.scale = working_size(H, W, max_width, min_width)
        self.size = (h, w)
        self.backend, self.model_path, self.preset = backend, model_path, preset
        if backend == "dis":  # grey at max_width, then an integer cubic upscale (bit-exact with earlier releases)
            gray = to_gray_small(frames, max_width)[0]
            if gray.shape[1:] != (h, w):
                gray = np.stack([cv2.resize(x, (w, h), interpolation=cv2.INTER_CUBIC) for x in gray])
            self.gray, self.rgb = gray, None
        else:
            interp = cv2.INTER_AREA if w < W else cv2.INTER_CUBIC
            self.rgb = np.stack([f if (w, h) == (W, H) else cv2.resize(f, (w, h), interpolation=interp)
                                 for f in frames])
            self.gray = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in self.rgb])
        self._sess = raft_session(model_path) if backend == "onnx" else None
        self._memo = {}
        self.fuse_fine = bool(fuse_fine) and backend == "dis"

    @property
    def num_frames(self):
        return len(self.gray)

    def __call__(self, f, g):
        """Flow [h,w,2] from frame ``f`` to frame ``g`` at the working size (memoised)."""
        key = (int(f), int(g))
        out = self._memo.get(key)
        if out is None:
            if self.fuse_fine:
                out, back = dis_fused(self.gray[f], self.gray[g], self.preset)
                self._memo[key[::-1]] = back
            elif self._sess is None:
                out = dis_flow(self.gray[f], self.gray[g], self.preset)
            else:
                out = raft_flow(self._sess, self.rgb[f], self.rgb[g])
            self._memo[key] = out
        return out

    def resampled(self, f, g, size):
        """Flow ``f -> g`` resized to ``size = (h, w)`` with the vectors rescaled -> [h,w,2]."""
        return resize_flow(self(f, g), size)

    def forget(self, f, g):
        """Drop the memoised flow ``f -> g`` (a consumer that keeps its own copy)."""
        self._memo.pop((int(f), int(g)), None)


class FusedFlowSource:
    """Per pixel the better of a learned flow and DIS: the one whose warp matches the image.

    A learned flow (RAFT-small) and DIS fail in different places. On the large-motion
    generated scene (one-frame error against ground truth, 8 frame pairs, docs/benchmarks.md)
    RAFT-small at its affordable 240-px width is worse than DIS on the static scene (0.53 vs
    0.10 px median: it under-estimates the camera's flow on fine texture, symmetrically both
    ways, so the forward-backward check cannot see it; chained over a clip the drift wrecks the
    depth anchors and the motion mask) and, on moving parts, better on some pixels and worse on
    others. Each pixel here takes the flow with the lower photometric residual
    (:func:`photometric_residual`: how well frame ``g`` pulled back along the flow matches frame
    ``f``), which sees a wrong flow on texture whichever way it errs.

    Parameters
    ----------
    dis : FlowSource, backend ``dis`` (its working size and grey frames are this source's)
    learned : FlowSource, backend ``onnx`` (any working size: resampled to ``dis.size``)
    window : side of the box that averages the residual (px)

    Attributes
    ----------
    size, scale, gray : those of ``dis``; ``picked`` : running share of pixels that took the
    learned flow (for the log)
    """

    def __init__(self, dis, learned, window=5):
        self.dis, self.learned, self.window = dis, learned, int(window)
        self.size, self.scale, self.gray = dis.size, dis.scale, dis.gray
        self.backend, self.model_path = "fused", learned.model_path
        self._memo = {}
        self._picked = [0, 0]

    @property
    def num_frames(self):
        return len(self.gray)

    @property
    def picked(self):
        return self._picked[0] / max(self._picked[1], 1)

    def __call__(self, f, g):
        """Flow [h,w,2] from frame ``f`` to frame ``g`` at ``dis.size`` (memoised)."""
        key = (int(f), int(g))
        out = self._memo.get(key)
        if out is None:
            d = self.dis(f, g)
            r = self.learned.resampled(f, g, self.size)
            a, b = self.gray[f].astype(np.float32), self.gray[g].astype(np.float32)
            take = photometric_residual(a, b, r, self.window) < photometric_residual(a, b, d, self.window)
            self._picked[0] += int(take.sum()); self._picked[1] += take.size
            out = self._memo[key] = np.where(take[..., None], r, d)
            self.dis.forget(f, g); self.learned.forget(f, g)  # kept once, fused
        return out

    def resampled(self, f, g, size):
        """Flow ``f -> g`` resized to ``size = (h, w)`` with the vectors rescaled -> [h,w,2]."""
        return resize_flow(self(f, g), size)


def resize_flow(flow, size):
    """Flow ``[h0,w0,2]`` resized to ``size = (h, w)``, vectors rescaled to the new pixels -> [h,w,2]."""
    import cv2

    h, w = size
    if flow.shape[:2] == (h, w):
        return flow
    out = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)
    out[..., 0] *= w / flow.shape[1]; out[..., 1] *= h / flow.shape[0]
    return out


def photometric_residual(a, b, flow, window=5):
    """Box-averaged ``|a(p) - b(p + flow(p))|`` [h,w] float32 for grey ``a``, ``b`` [h,w] and a
    flow ``[h,w,2]`` from ``a`` to ``b`` (:func:`pull_back`)."""
    import cv2

    pulled = pull_back(np.asarray(b, np.float32), flow)
    return cv2.blur(np.abs(np.asarray(a, np.float32) - pulled), (window, window))


def bilinear(img, xy):
    """Sample ``img [h,w,C]`` at continuous coords ``xy [P,2]`` (edge-clamped) -> [P,C]."""
    h, w = img.shape[:2]
    x = np.clip(xy[:, 0] - 0.5, 0, w - 1)
    y = np.clip(xy[:, 1] - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy).astype(np.float32)
