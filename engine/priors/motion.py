"""Foreground / dynamic prior ``p_dyn [F,H,W]`` in [0,1].

``motion`` backend (weight-free). With ``depth``: one-frame DIS flows (<= ``max_width`` px,
forward and backward; or a shared learned flow, ``source``, resampled to that size) are chained to t±1, t±2, t±4 (a direct k-frame DIS flow fails on
repetitive texture); a pixel counts for a gap only while every step is forward-backward
consistent and stays in view. Per gap two residuals, each divided by its per-frame robust scale
(median + 1.4826·MAD of the valid pixels, floored at 0.25 px resp. 0.1 px per frame of gap):
``|flow − rigid flow|`` (back-project with depth, move by the relative pose, project) and the
depth-free Sampson distance to the epipolar geometry (depth inside moving objects carries no
anchors and is filled from the static surroundings, which can cancel most of the residual —
the epipolar test does not depend on it). The per-pixel max of the two is averaged over the valid
gaps, down-weighted where the image has no texture (``e/(e+tex_eps)`` as below: DIS flow is
unreliable there), averaged over ``t_win`` (5) frames, then segmented per frame: 5×5 blur, hysteresis
(``lo`` 1.5 / ``hi`` 4, in robust-scale units), closing (``close_px``), opening, filling of holes
enclosed by the region (< 25 % of the image: slowly moving interiors such as a waving flag only
show motion on their border), erosion by ``trim_px`` (DIS smears motion a few pixels into the
background), a 5×5 blur and a guided filter with the RGB frame as guide (radius ``trim_px``,
eps 1e-3: the mask edge snaps to the image edge). Structuring sizes are in working-resolution px.
Beside it (``photometric``, default on) a colour residual of the static-scene hypothesis
(:func:`_photometric_residual`: each pixel warped to f±k with the depth prior and the relative
pose, the smaller of the two colour differences, robustly normalised per gap) is segmented on
its own -- no temporal box, no trim, a 3-px opening, a 2-px snap -- and OR-ed with the flow
mask: flow is not forward-backward consistent on thin fast parts (a swinging forearm), which
the flow mask therefore missed. Then ``passes`` (2) = one mask -> depth -> mask pass: the depth is re-densified from its static
part only (every working pixel outside the mask is an anchor of the sparse prior's edge-aware
fill; inside the mask it is filled from the static surroundings, no longer from anchors that sat
on a moving object and leaked from there onto the background around it) and the residual is
recomputed on it with the same flows.
Without depth (per-pixel, previous algorithm): Sampson residual to f±1, down-weighted by
``e/(e+tex_eps)`` where ``e`` is the local gradient energy, normalised robustly per frame
(``tau = max(min_px, median + k*1.4826*MAD)``), mapped softly to [0,1] (logistic, centre
``tau``) and smoothed temporally (3-frame box) and spatially.

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


def _affine3(A, b, P):
    """``P [h,w,3] @ A.T + b`` with float32 element-wise ops (no BLAS call per small matmul)."""
    return np.stack([P[..., 0] * A[i, 0] + P[..., 1] * A[i, 1] + P[..., 2] * A[i, 2] + b[i] for i in range(3)], -1)


def _camera_points(Kinv, depth, pix):
    """Camera-space points ``[h,w,3]`` of the working-resolution pixels ``pix [h,w,3]``
    (``Kinv`` at working resolution) at the full-resolution ``depth [H,W]``, area-resized."""
    import cv2

    h, w = pix.shape[:2]
    rays = _affine3(Kinv.astype(np.float32), np.zeros(3, np.float32), pix)
    return rays * cv2.resize(depth.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)[..., None]


def _rigid_flow(X, Kg, rel, pix):
    """Flow [h,w,2] that the relative camera motion ``rel`` induces on camera-space points ``X [h,w,3]``."""
    pr = _affine3((Kg @ rel[:3, :3]).astype(np.float32), (Kg @ rel[:3, 3]).astype(np.float32), X)
    return pr[..., :2] / np.maximum(pr[..., 2:], 1e-6) - pix[..., :2]


def _sampson_fast(flow, Fm, pix):
    """Sampson distance [h,w] of (pix, pix + flow) to the fundamental matrix ``Fm``."""
    x2 = pix.copy(); x2[..., :2] += flow
    Fm = Fm.astype(np.float32); z = np.zeros(3, np.float32)
    Fx1 = _affine3(Fm, z, pix); Ftx2 = _affine3(Fm.T.copy(), z, x2)
    num = np.abs(x2[..., 0] * Fx1[..., 0] + x2[..., 1] * Fx1[..., 1] + Fx1[..., 2])
    den = Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-12))


def _fill_holes(b, max_frac=0.25):
    """Fill holes (regions enclosed by ``b``) smaller than ``max_frac`` of the image."""
    import cv2

    out = b.astype(np.uint8).copy()
    cs, hier = cv2.findContours(out.copy(), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hier is None:
        return out
    holes = [c for i, c in enumerate(cs) if hier[0][i][3] >= 0 and cv2.contourArea(c) < max_frac * b.size]
    if holes:
        cv2.drawContours(out, holes, -1, 1, -1)
    return out


def _hysteresis(lo, hi):
    import cv2

    n, lab = cv2.connectedComponents(lo.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[np.unique(lab[hi & lo])] = True
    keep[0] = False
    return keep[lab]


RIGID_FLOOR, SAMPSON_FLOOR = 0.25, 0.1


def _pair_flows(gray, fb_px=1.0, source=None):
    """One-frame DIS flows forward/backward and their forward-backward consistency masks.

    ``source`` : :class:`~engine.priors.flow.FlowSource`, optional (default: DIS on ``gray``).
    Returns ``(fw, bw, okf, okb)``: lists of F-1 ``[h,w,2]`` flows (t -> t+1, t+1 -> t) and float32
    ``[h,w]`` masks (1 where ``|fwd + bwd(p + fwd)| < fb_px + 0.05 |fwd|``). Independent of depth,
    so the mask -> depth -> mask pass reuses them.
    """
    import cv2

    F, h, w = gray.shape
    if source is None:
        fw = [_flow.dis_flow(gray[f], gray[f + 1], "medium") for f in range(F - 1)]
        bw = [_flow.dis_flow(gray[f + 1], gray[f], "medium") for f in range(F - 1)]
    else:  # a shared (e.g. learned) flow, resampled to this working size
        fw = [source.resampled(f, f + 1, (h, w)) for f in range(F - 1)]
        bw = [source.resampled(f + 1, f, (h, w)) for f in range(F - 1)]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))

    def fb_ok(a, b):
        e = a + cv2.remap(b, xs + a[..., 0], ys + a[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return (np.hypot(e[..., 0], e[..., 1]) < fb_px + 0.05 * np.hypot(a[..., 0], a[..., 1])).astype(np.float32)

    return fw, bw, [fb_ok(fw[f], bw[f]) for f in range(F - 1)], [fb_ok(bw[f], fw[f]) for f in range(F - 1)]


def _multigap_residual(flows, K, w2c, depth, S, s, gaps=(1, 2, 4)):
    """Normalised residual (max of rigid-flow and Sampson) over frame gaps ±``gaps`` -> [F,h,w].

    ``flows`` from :func:`_pair_flows`. Flow to t±k is the chain of the one-frame DIS flows
    (one-frame flow is reliable on repetitive texture where a direct k-frame flow is not); a
    pixel counts for gap k only while every step is forward-backward consistent and stays in
    the image (occlusions and out-of-view points excluded). Each gap's residual is divided by
    its per-frame robust scale (median + 1.4826 MAD, at least RIGID_FLOOR / SAMPSON_FLOOR px per
    frame of gap), the max of the two is taken per pixel and the valid gaps are averaged.
    """
    import cv2

    fw, bw, okf, okb = flows
    F = len(fw) + 1
    h, w = fw[0].shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))

    def samp(img, d):
        return cv2.remap(img, xs + d[..., 0], ys + d[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    Ks = np.einsum("ij,fjk->fik", S, K); Kinv = np.linalg.inv(Ks); c2w = np.linalg.inv(w2c)
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs)], -1)  # continuous coords
    num = np.zeros((F, h, w), np.float32); den = np.zeros((F, h, w), np.float32)
    for f in range(F):
        X = _camera_points(Kinv[f], depth[f], pix)
        obs = []  # (gap k, target frame g, chained flow, valid)
        for sgn in (1, -1):
            acc = np.zeros((h, w, 2), np.float32); ok = np.ones((h, w), bool); g = f
            for k in range(1, max(gaps) + 1):
                if not 0 <= g + sgn < F:
                    break
                fl, o = (fw[g], okf[g]) if sgn > 0 else (bw[g - 1], okb[g - 1])
                if k > 1:
                    fl, o = samp(fl, acc), samp(o, acc)
                acc = acc + fl; ok &= o > 0.99; g += sgn
                if k not in gaps:
                    continue
                v = ok & (xs + acc[..., 0] >= 0) & (xs + acc[..., 0] <= w - 1) & (ys + acc[..., 1] >= 0) & (ys + acc[..., 1] <= h - 1)
                if v.sum() >= 0.05 * v.size:
                    obs.append((k, g, acc, v))
        for k, g, acc, v in obs:
            rel = w2c[g] @ c2w[f]
            t = rel[:3, 3]
            tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            d = acc - _rigid_flow(X, Ks[g], rel, pix)
            z = 0.0
            for r, floor in ((np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2), RIGID_FLOOR),
                             (_sampson_fast(acc, Kinv[g].T @ tx @ rel[:3, :3] @ Kinv[f], pix), SAMPSON_FLOOR)):
                rv = r[v][::4]; med = np.median(rv); mad = 1.4826 * np.median(np.abs(rv - med))
                z = np.maximum(z, r / max(med + mad, floor * s * k))
            num[f] += np.where(v, z, 0); den[f] += v
    return num / np.maximum(den, 1e-6)


PHOTO_FLOOR = 0.02  # colour residual scale floor (fraction of the [0, 1] range)


def _photometric_residual(rgb, K, w2c, depth, S, gaps=(1, 2, 4)):
    """Normalised colour residual of the static-scene hypothesis over frame gaps -> [F,h,w].

    Each pixel of frame f is back-projected with the depth prior (which sees the static scene)
    and looked up in frames f±k: where the static scene is what the pixel shows, the colours
    agree; where a moving object covers the pixel at f -- or covered its static point at f±k --
    they do not. Taking the smaller of the two residuals (f-k and f+k; "three-frame
    differencing" with the camera motion compensated) keeps the object where it is at f and
    drops the ghosts where it was at f±k. Unlike the flow residual this needs no
    forward-backward consistent flow, so it sees thin fast parts (a swinging forearm) that
    flow loses. Each gap's residual is divided by its per-frame robust scale (median + 1.4826
    MAD, at least ``PHOTO_FLOOR``); the gaps are averaged.

    rgb : uint8 [F,h,w,3] frames at working resolution; K [F,3,3], w2c [F,4,4] at full
    resolution (``S`` maps K to working resolution); depth [F,H,W] full resolution.
    """
    import cv2

    F, h, w = rgb.shape[:3]
    img = np.stack([cv2.GaussianBlur(x.astype(np.float32) / 255.0, (3, 3), 0) for x in rgb])
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs)], -1)
    Ks = np.einsum("ij,fjk->fik", S, K); Kinv = np.linalg.inv(Ks); c2w = np.linalg.inv(w2c)
    out = np.zeros((F, h, w), np.float32)
    for f in range(F):  # per frame, whole-image warps (cv2.remap)
        X = _camera_points(Kinv[f], depth[f], pix)
        num = np.zeros((h, w), np.float32); den = np.zeros((h, w), np.float32)
        for k in gaps:
            sides = []
            for g in (f - k, f + k):
                if not 0 <= g < F:
                    continue
                rel = w2c[g] @ c2w[f]
                pr = _affine3((Ks[g] @ rel[:3, :3]).astype(np.float32), (Ks[g] @ rel[:3, 3]).astype(np.float32), X)
                uv = pr[..., :2] / np.maximum(pr[..., 2:], 1e-6) - 0.5
                v = (pr[..., 2] > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
                warped = cv2.remap(img[g], uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                sides.append((np.abs(warped - img[f]).mean(-1), v))
            if not sides:
                continue
            r = np.where(sides[0][1], sides[0][0], np.inf)
            for rr, vv in sides[1:]:
                r = np.minimum(r, np.where(vv, rr, np.inf))
            valid = np.isfinite(r)
            if valid.sum() < 0.05 * valid.size:
                continue
            rv = r[valid][::4]; med = np.median(rv); mad = 1.4826 * np.median(np.abs(rv - med))
            num += np.where(valid, r / max(med + mad, PHOTO_FLOOR), 0); den += valid
        out[f] = num / np.maximum(den, 1e-6)
    return out


def _refill(frames, depth, dyn, S, max_width):
    """``depth`` re-densified from its static part only -> [F,H,W].

    Every working-resolution pixel with ``dyn < 0.5`` is an anchor of :func:`depth.densify`
    (the same edge-aware fill the ``sparse`` depth prior uses), the mask carries none: inside it
    the depth comes from the static surroundings, no longer from the anchors that sat on a moving
    object (a slowly moving object often triangulates as static) and leaked from there onto the
    background around it.
    """
    from .depth import densify

    F, H, W = depth.shape
    h, w = int(round(H * S[1, 1])), int(round(W * S[0, 0]))
    ys, xs = np.mgrid[0:h, 0:w]
    u, v = (xs + 0.5) / S[0, 0], (ys + 0.5) / S[1, 1]  # continuous full-resolution coords
    iu, iv = np.clip(u.astype(int), 0, W - 1), np.clip(v.astype(int), 0, H - 1)
    out = np.empty((F, H, W), np.float32)
    for f in range(F):
        d = depth[f, iv, iu]
        sel = (dyn[f, iv, iu] < 0.5) & (d > 0)
        out[f] = densify(frames[f], np.stack([u[sel], v[sel], d[sel]], 1), max_width)[0] if sel.sum() >= 3 else depth[f]
    return out


def _texture_weight(gray, tex_eps=1e-3):
    """``e / (e + tex_eps)`` [h,w], ``e`` = 9×9 mean squared gradient of the grey frame in [0,1].

    DIS flow is unreliable where the image has no texture (it is ~0 or noise there whatever the
    motion, e.g. a white table top), so the residual there is no evidence of motion: it is
    down-weighted (moving objects' texture-less interiors are recovered by the hole filling)."""
    import cv2

    g = gray.astype(np.float32) / 255.0
    te = cv2.boxFilter(cv2.Sobel(g, cv2.CV_32F, 1, 0) ** 2 + cv2.Sobel(g, cv2.CV_32F, 0, 1) ** 2, -1, (9, 9))
    return te / (te + tex_eps)


def _snap(m, guide, radius, eps=1e-3):
    """Soft masks [F,h,w] snapped to the image edges: guided filter (He et al.) with the RGB frame
    (in [0,1]) as guide, window ``radius`` (the DIS smear width, ``trim_px``): where the frame has
    an edge the mask follows it, where it has none the mask is smoothed. ``eps`` 1e-3: edges of
    contrast above ~0.03 are kept (IoU within +-0.01 on the generated scenes over eps 1e-4..1e-2)."""
    import cv2

    return np.stack([np.clip(cv2.ximgproc.guidedFilter(guide[f].astype(np.float32) / 255.0, m[f], int(radius), eps), 0, 1)
                     for f in range(len(m))]).astype(np.float32)


def _temporal_box(sc, t_win):
    """Mean of ``sc [F,h,w]`` over a window of ``t_win`` frames (edges repeated)."""
    F = len(sc)
    r = t_win // 2
    if r == 0:
        return sc
    pad = np.concatenate([sc[:1]] * r + [sc] + [sc[-1:]] * r)
    return np.mean([pad[i:i + F] for i in range(2 * r + 1)], 0)


def _segment(sc, t_win=5, lo=1.5, hi=4.0, close_px=15, trim_px=7, open_px=5):
    """Normalised residual [F,h,w] -> soft mask [F,h,w] (temporal box, hysteresis, morphology)."""
    import cv2

    F = len(sc)
    sc = _temporal_box(sc, t_win)

    def ell(d):
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (max(3, int(d) | 1),) * 2)

    out = np.empty_like(sc)
    for f in range(F):
        x = cv2.GaussianBlur(sc[f], (5, 5), 0)
        b = _hysteresis(x > lo, x > hi).astype(np.uint8)
        b = cv2.morphologyEx(b, cv2.MORPH_CLOSE, ell(close_px))
        b = cv2.morphologyEx(b, cv2.MORPH_OPEN, ell(open_px))
        b = _fill_holes(b)
        if trim_px:  # DIS smears object motion a few px into the background
            b = cv2.erode(b, ell(trim_px))
        out[f] = cv2.GaussianBlur(b.astype(np.float32), (5, 5), 0)
    return out


def motion_mask(frames, K, w2c, depth=None, max_width=320, k=3.0, min_px=1.0, tex_eps=1e-3, reporter=None,
                gaps=(1, 2, 4), lo=1.5, hi=4.0, t_win=5, close_px=7, trim_px=7, passes=2, source=None,
                photometric=True):
    """Weight-free motion prior (see module docstring) -> float32 [F,H,W].

    With depth, ``passes`` segmentations (mask -> depth -> mask): each one after the first
    recomputes the residual on the depth re-densified from the static part of the previous mask
    (:func:`_refill`); the flows are computed once. ``source`` : a shared
    :class:`~engine.priors.flow.FlowSource` (default: DIS at ``max_width``).
    """
    import cv2

    F, H, W, _ = frames.shape
    gray, s = _flow.to_gray_small(frames, max_width)
    h, w = gray.shape[1:]
    S = np.diag([w / W, h / H, 1.0])  # K at working resolution (continuous coords scale exactly)
    out = np.zeros((F, H, W), np.float32)
    if depth is not None and F >= 2:
        flows = _pair_flows(gray, source=source)
        texw = np.stack([_texture_weight(x, tex_eps) for x in gray])
        guide = np.stack([cv2.resize(x, (w, h), interpolation=cv2.INTER_AREA) for x in frames]) if (w, h) != (W, H) else frames
        npass = max(1, int(passes))
        for i in range(npass):
            if i:
                depth = _refill(frames, depth, out, S, max_width)
            sc = _multigap_residual(flows, K, w2c, depth, S, s, gaps) * texw
            m = _segment(sc, t_win, lo, hi, close_px, trim_px)
            if trim_px:
                m = _snap(m, guide, trim_px)
            if photometric:
                # the colour residual is segmented on its own: no temporal box (it marks where
                # the object is at f; a box would smear a fast one along its path), no trim, a
                # 3-px opening and a 2-px snap (nothing smears it; the trim, a 5-px opening and
                # the trim-wide guided filter each erased thin parts such as a swinging forearm)
                pm = _segment(_photometric_residual(guide, K, w2c, depth, S, gaps), 1, lo, hi, close_px, 0, 3)
                m = np.maximum(m, _snap(pm, guide, 2) if trim_px else pm)
            out = np.clip(np.stack([cv2.resize(x, (W, H), interpolation=cv2.INTER_LINEAR) for x in m]), 0, 1)
            if reporter is not None:
                reporter.progress("dynamic_mask", (i + 1) * F // npass, F)
        return out.astype(np.float32)
    res = np.zeros((F, h, w), np.float32)
    for f in range(F):
        nbrs = [g for g in (f - 1, f + 1) if 0 <= g < F]
        acc = []
        for g in nbrs:
            fl = _flow.dis_flow(gray[f], gray[g], "medium") if source is None else source.resampled(f, g, (h, w))
            rel = w2c[g] @ np.linalg.inv(w2c[f])
            acc.append(_sampson(fl, S @ K[f], S @ K[g], rel))
        res[f] = np.mean(acc, 0) if acc else 0.0
        res[f] *= _texture_weight(gray[f], tex_eps)
        if reporter is not None:
            reporter.progress("dynamic_mask", f + 1, F)
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
                 foreground_classes=None, reporter=None, source=None):
    """Dynamic / foreground probability per pixel.

    Parameters
    ----------
    frames : uint8 [F,H,W,3]; K : [F,3,3]; w2c : [F,4,4]; depth : [F,H,W], optional
    backend : 'motion' | 'onnx'
    source : :class:`~engine.priors.flow.FlowSource`, optional (``motion``: the flow to use; default DIS)

    Returns
    -------
    float32 [F,H,W] in [0,1]
    """
    frames = np.asarray(frames)
    if backend == "motion":
        return motion_mask(frames, np.asarray(K, np.float64), np.asarray(w2c, np.float64), depth, max_width,
                           reporter=reporter, source=source)
    if backend == "onnx":
        return onnx_mask(frames, model_path, foreground_classes, reporter=reporter)
    raise InputError(f"unknown dynamic-mask backend {backend!r}.", fix="Use 'motion' or 'onnx'.")
