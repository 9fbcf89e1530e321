"""Per-patch semantic tokens: ONNX ViT features or a hand-crafted descriptor.

Both backends return a :class:`TokenGrid` with the same contract: ``tokens [F,Gh,Gw,D]``
float32, L2-normalised over ``D``; ``patch_centers [Gh,Gw,2]`` (x, y) in continuous pixel
coordinates of the *original* frame; ``patch_size_px`` (w, h) of one patch in original pixels.

ONNX backend: any ViT feature extractor whose first output is ``[B, N, D]`` tokens
(``N = extra + Gh*Gw``; the leading ``extra`` CLS/register tokens are stripped) or a
``[B, D, Gh, Gw]`` feature map. The frame is resized (aspect not kept) to the model's input
size (graph shape or sidecar ``input_size``), ImageNet-normalised unless the sidecar says
otherwise. Tested with the DINOv2 ViT-S/14 export at 224 px (input ``input_image``
[B,3,224,224], output [B,257,384] = CLS + 16x16 patches).

Hand-crafted backend (weight-free), per patch of ``patch_size`` px on the frame resized to a
multiple of the patch size: Lab mean (3) and std (3), an 8-bin magnitude-weighted gradient
orientation histogram (8), an 8-neighbour LBP-style sign histogram (8) and log Laplacian
energy (1): D = 23, each group scaled to comparable magnitude, then L2-normalised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from . import onnx_util


@dataclass
class TokenGrid:
    """Per-patch tokens. ``tokens [F,Gh,Gw,D]``, ``patch_centers [Gh,Gw,2]``, ``patch_size_px (w,h)``."""

    tokens: np.ndarray
    patch_centers: np.ndarray
    patch_size_px: tuple


def _check_frames(frames):
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise InputError(f"frames must be uint8 [F,H,W,3], got {frames.dtype} {frames.shape}.")
    return frames


def _centers(H, W, gh, gw):
    xs = (np.arange(gw, dtype=np.float32) + 0.5) * (W / gw)
    ys = (np.arange(gh, dtype=np.float32) + 0.5) * (H / gh)
    return np.stack(np.meshgrid(xs, ys), axis=-1).astype(np.float32)


def _l2(x):
    return (x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-8)).astype(np.float32)


def _patches(img, gh, gw, p):
    """[H',W',C] -> [gh,gw,p*p,C] (vectorised reshape)."""
    c = img.shape[-1]
    return img.reshape(gh, p, gw, p, c).transpose(0, 2, 1, 3, 4).reshape(gh, gw, p * p, c)


def handcrafted_tokens(frames, patch_size=16):
    """Weight-free descriptor per patch; see module docstring. Returns :class:`TokenGrid`."""
    import cv2

    frames = _check_frames(frames)
    F, H, W, _ = frames.shape
    p = int(patch_size)
    gh, gw = max(1, int(round(H / p))), max(1, int(round(W / p)))
    out = np.empty((F, gh, gw, 23), np.float32)
    for f in range(F):
        img = cv2.resize(frames[f], (gw * p, gh * p), interpolation=cv2.INTER_AREA)
        lab = cv2.cvtColor(img.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab) / np.float32(100.0)
        P = _patches(lab, gh, gw, p)
        mean, std = P.mean(2), P.std(2)
        gray = lab[..., 0]
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
        mag = np.hypot(gx, gy)
        ang = np.mod(np.arctan2(gy, gx), np.pi)  # unsigned orientation
        b = np.minimum((ang / np.pi * 8).astype(np.int64), 7)
        onehot = (b[..., None] == np.arange(8)) * mag[..., None]
        hog = _patches(onehot.astype(np.float32), gh, gw, p).sum(2)
        hog = hog / np.maximum(hog.sum(-1, keepdims=True), 1e-6)
        pad = np.pad(gray, 1, mode="edge")
        shifts = [(0, 0), (0, 1), (0, 2), (1, 2), (2, 2), (2, 1), (2, 0), (1, 0)]
        hh, ww = gray.shape
        lbp = np.stack([(pad[dy:dy + hh, dx:dx + ww] > gray + 0.01) for dy, dx in shifts], -1).astype(np.float32)
        lbp = _patches(lbp, gh, gw, p).mean(2)
        lap = cv2.Laplacian(gray, cv2.CV_32F, ksize=3)
        lap_e = np.log1p(100.0 * _patches((lap ** 2)[..., None], gh, gw, p).mean(2))
        feat = np.concatenate([mean * 2.0, std * 4.0, hog, lbp * 0.5, lap_e * 0.5], -1)
        out[f] = feat
    return TokenGrid(_l2(out), _centers(H, W, gh, gw), (W / gw, H / gh))


def onnx_tokens(frames, model_path, patch_size=14, reporter=None):
    """ViT features from an ONNX model; see module docstring. Returns :class:`TokenGrid`."""
    frames = _check_frames(frames)
    F, H, W, _ = frames.shape
    sess = onnx_util.load_session(model_path)
    side = onnx_util.read_sidecar(model_path)
    name, layout, (h, w), fixed = onnx_util.image_input_spec(sess, side, (224, 224))
    p = int(side.get("patch_size", patch_size))
    gh, gw = h // p, w // p
    mean = side.get("mean", onnx_util.IMAGENET_MEAN)
    std = side.get("std", onnx_util.IMAGENET_STD)
    chunks = []
    step = 1 if fixed else 8
    for i in range(0, F, step):
        batch = onnx_util.prepare_images(frames[i:i + step], (h, w), layout, mean, std)
        chunks.append(sess.run(None, {name: batch})[0])
        if reporter is not None:
            reporter.progress("tokens", min(i + step, F), F)
    out = np.concatenate(chunks, 0).astype(np.float32)
    if out.ndim == 3:
        n = out.shape[1]
        if n < gh * gw:
            raise InputError(f"model returns {n} tokens, fewer than the {gh}x{gw} patch grid.", model_path,
                             "Set patch_size/input_size in the sidecar JSON.")
        out = out[:, n - gh * gw:].reshape(-1, gh, gw, out.shape[2])
    elif out.ndim == 4:
        gh, gw = out.shape[2], out.shape[3]
        out = out.transpose(0, 2, 3, 1)
    else:
        raise InputError(f"unexpected token output shape {out.shape}.", model_path,
                         "Export a model returning [B,N,D] tokens or a [B,D,Gh,Gw] feature map.")
    return TokenGrid(_l2(out), _centers(H, W, gh, gw), (W / gw, H / gh))


def extract_tokens(frames, backend="handcrafted", model_path=None, patch_size=None, reporter=None):
    """Per-patch tokens for every frame.

    Parameters
    ----------
    frames : uint8 [F,H,W,3] RGB
    backend : 'handcrafted' | 'onnx'
    model_path : path of the ONNX ViT (backend 'onnx')
    patch_size : int, default 16 (handcrafted) / 14 (onnx, overridden by the sidecar)

    Returns
    -------
    TokenGrid
    """
    if backend == "handcrafted":
        return handcrafted_tokens(frames, 16 if patch_size is None else patch_size)
    if backend == "onnx":
        return onnx_tokens(frames, model_path, 14 if patch_size is None else patch_size, reporter)
    raise InputError(f"unknown tokens backend {backend!r}.", fix="Use 'handcrafted' or 'onnx'.")
