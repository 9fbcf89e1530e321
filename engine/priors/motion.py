"""Foreground / dynamic prior ``p_dyn [F,H,W]`` in [0,1].

``motion`` backend (weight-free): DIS flow (<= ``max_width`` px) from each frame to its
neighbours (f-1 and f+1) is compared with what the camera explains: with ``depth``, the
rigid flow from K, w2c and depth (back-project, move to the neighbour camera, project);
without depth, the Sampson distance to the epipolar geometry (F from the cameras). The
per-pixel residual (px, mean over the neighbours, down-weighted by ``e/(e+tex_eps)`` where
``e`` is the local gradient energy: flow is meaningless without texture) is normalised robustly per frame
(``tau = max(min_px, median + k*1.4826*MAD)``), mapped softly to [0,1]
(logistic, centre ``tau``) and smoothed temporally (3-frame box) and spatially.

``onnx`` backend: a semantic segmenter (e.g. DeepLabv3 MobileNet, PASCAL 21 classes:
input [1,257,257,3] NHWC RGB in [-1,1], output [1,257,257,21] scores). Layout is detected
from the input shape (NHWC -> [-1,1] scaling, NCHW -> ImageNet mean/std) or the sidecar;
the class axis is the output axis whose size differs from the two equal spatial ones (else
sidecar ``output_layout`` 'HWC'|'CHW', else the input layout). ``p = 1 - softmax[background]``
(class ``background_class``, default 0) or the summed probability of
``foreground_classes``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from . import flow as _flow
from . import onnx_util


def _rigid_residual(flow, depth_s, Ks_f, Ks_g, rel):
    h, w = flow.shape[:2]
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3)
    rays = pix @ np.linalg.inv(Ks_f).T
    X = rays * depth_s.reshape(-1, 1)
    Y = X @ rel[:3, :3].T + rel[:3, 3]
    pr = Y @ Ks_g.T
    uv = pr[:, :2] / np.maximum(pr[:, 2:], 1e-6)
    rigid = (uv - pix[:, :2]).reshape(h, w, 2)
    return np.linalg.norm(flow - rigid, axis=-1)


def _sampson(flow, Ks_f, Ks_g, rel):
    h, w = flow.shape[:2]
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Fm = np.linalg.inv(Ks_g).T @ tx @ R @ np.linalg.inv(Ks_f)
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x1 = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3)
    x2 = x1.copy(); x2[:, :2] += flow.reshape(-1, 2)
    Fx1 = x1 @ Fm.T; Ftx2 = x2 @ Fm
    num = np.sum(x2 * Fx1, 1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12)).reshape(h, w)


def motion_mask(frames, K, w2c, depth=None, max_width=320, k=3.0, min_px=1.0, tex_eps=1e-3, reporter=None):
    """Weight-free motion prior (see module docstring) -> float32 [F,H,W]."""
    import cv2

    F, H, W, _ = frames.shape
    gray, s = _flow.to_gray_small(frames, max_width)
    h, w = gray.shape[1:]
    S = np.diag([w / W, h / H, 1.0])  # K at working resolution (continuous coords scale exactly)
    res = np.zeros((F, h, w), np.float32)
    for f in range(F):
        nbrs = [g for g in (f - 1, f + 1) if 0 <= g < F]
        acc = []
        for g in nbrs:
            fl = _flow.dis_flow(gray[f], gray[g], "medium")
            rel = w2c[g] @ np.linalg.inv(w2c[f])
            Kf, Kg = S @ K[f], S @ K[g]
            if depth is not None:
                ds = cv2.resize(depth[f].astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
                acc.append(_rigid_residual(fl, ds, Kf, Kg, rel))
            else:
                acc.append(_sampson(fl, Kf, Kg, rel))
        res[f] = np.mean(acc, 0) if acc else 0.0
        # flow is unreliable on texture-less areas (it stays ~0 there): down-weight their residual
        g = gray[f].astype(np.float32) / 255.0
        te = cv2.boxFilter(cv2.Sobel(g, cv2.CV_32F, 1, 0) ** 2 + cv2.Sobel(g, cv2.CV_32F, 0, 1) ** 2, -1, (9, 9))
        res[f] *= te / (te + tex_eps)
        if reporter is not None:
            reporter.progress("dynamic_mask", f + 1, F)
    out = np.zeros((F, H, W), np.float32)
    prob = np.zeros_like(res)
    for f in range(F):
        r = res[f]
        med = np.median(r); mad = 1.4826 * np.median(np.abs(r - med))
        tau = max(min_px * s, med + k * mad)
        prob[f] = 1.0 / (1.0 + np.exp(-(r - tau) / (0.25 * tau)))
    if F >= 3:
        pad = np.concatenate([prob[:1], prob, prob[-1:]])
        prob = (pad[:-2] + pad[1:-1] + pad[2:]) / 3.0
    for f in range(F):
        out[f] = cv2.resize(cv2.GaussianBlur(prob[f], (5, 5), 0), (W, H), interpolation=cv2.INTER_LINEAR)
    return np.clip(out, 0, 1).astype(np.float32)


def onnx_mask(frames, model_path, foreground_classes=None, background_class=None, reporter=None):
    """Segmentation prior from an ONNX model (see module docstring) -> float32 [F,H,W]."""
    import cv2

    sess = onnx_util.load_session(model_path)
    side = onnx_util.read_sidecar(model_path)
    name, layout, size, fixed = onnx_util.image_input_spec(sess, side, (257, 257))
    if layout == "NHWC":
        mean, std = side.get("mean", (0.5, 0.5, 0.5)), side.get("std", (0.5, 0.5, 0.5))
    else:
        mean, std = side.get("mean", onnx_util.IMAGENET_MEAN), side.get("std", onnx_util.IMAGENET_STD)
    fg = foreground_classes if foreground_classes is not None else side.get("foreground_classes")
    bg = int(background_class if background_class is not None else side.get("background_class", 0))
    F, H, W, _ = frames.shape
    out = np.empty((F, H, W), np.float32)
    for f in range(F):
        x = onnx_util.prepare_images(frames[f:f + 1], size, layout, mean, std)
        y = np.asarray(sess.run(None, {name: x})[0], np.float32)[0]
        if y.ndim == 2:
            y = y[..., None]
        first = side.get("output_layout", "").upper()
        if first:
            class_first = first == "CHW"
        elif y.shape[0] == y.shape[1] != y.shape[2] or y.shape[2] == 1:
            class_first = False
        elif y.shape[1] == y.shape[2] != y.shape[0] or y.shape[0] == 1:
            class_first = True
        else:
            class_first = layout == "NCHW"
        if class_first:  # [C,h,w] -> [h,w,C]
            y = y.transpose(1, 2, 0)
        if y.shape[-1] == 1:
            p = 1.0 / (1.0 + np.exp(-y[..., 0]))
        else:
            e = np.exp(y - y.max(-1, keepdims=True))
            sm = e / e.sum(-1, keepdims=True)
            p = sm[..., list(fg)].sum(-1) if fg else 1.0 - sm[..., bg]
        out[f] = cv2.resize(p.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
        if reporter is not None:
            reporter.progress("dynamic_mask", f + 1, F)
    return np.clip(out, 0, 1)


def dynamic_mask(frames, K, w2c, depth=None, backend="motion", model_path=None, max_width=320,
                 foreground_classes=None, reporter=None):
    """Dynamic / foreground probability per pixel.

    Parameters
    ----------
    frames : uint8 [F,H,W,3]; K : [F,3,3]; w2c : [F,4,4]; depth : [F,H,W], optional
    backend : 'motion' | 'onnx'

    Returns
    -------
    float32 [F,H,W] in [0,1]
    """
    frames = np.asarray(frames)
    if backend == "motion":
        return motion_mask(frames, np.asarray(K, np.float64), np.asarray(w2c, np.float64), depth, max_width,
                           reporter=reporter)
    if backend == "onnx":
        return onnx_mask(frames, model_path, foreground_classes, reporter=reporter)
    raise InputError(f"unknown dynamic-mask backend {backend!r}.", fix="Use 'motion' or 'onnx'.")
