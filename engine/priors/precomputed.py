"""Precomputed priors loaded from files (they bypass the built-in backends).

Formats (F, H, W = the clip's frame count and size):

* depth: ``.npy`` float [F,H,W] (scene units), or a folder of 16-bit PNGs (one per frame,
  sorted by name) with ``scale.json`` ``{"scale": s}`` in the folder: depth = png * s
  (0 = unknown, filled with the median).
* masks: a folder of 8-bit PNGs (one per frame, 0..255 -> 0..1) or ``.npy`` [F,H,W] in [0,1].
* tracks: ``.npz`` with ``xy`` [P,F,2] float pixels and ``visible`` [P,F] bool; optional
  ``confidence`` [P,F] and ``query_frame`` [P].

Every mismatch raises :class:`~engine.errors.InputError` naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from .tracks import Tracks


def _pngs(folder: Path, F):
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".png")
    if len(files) != F:
        raise InputError(f"has {len(files)} PNG files but the clip has {F} frames.", folder,
                         "Provide exactly one PNG per frame.")
    return files


def _read_png(path, flags):
    import cv2

    img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError("could not read the image.", path)
    return img


def _npy(path):
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"could not read ({exc}).", path) from exc


def _check(arr, shape, path, what):
    if arr.shape != shape:
        raise InputError(f"{what} has shape {arr.shape}, expected {shape} for this clip.", path,
                         "Recompute the prior for this clip or fix its resolution/frame count.")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} contains NaN or infinite values.", path)


def load_depth(path, shape):
    """Load precomputed depth -> float32 [F,H,W]. ``shape`` = (F, H, W)."""
    import cv2

    path = Path(path)
    F, H, W = shape
    if path.is_dir():
        sc = path / "scale.json"
        if not sc.is_file():
            raise InputError("16-bit depth PNGs need a scale.json with {\"scale\": ...}.", path)
        try:
            scale = float(json.loads(sc.read_text())["scale"])
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError("scale.json must contain a number 'scale'.", sc) from exc
        imgs = []
        for p in _pngs(path, F):
            im = _read_png(p, cv2.IMREAD_UNCHANGED)
            if im.dtype != np.uint16 or im.ndim != 2:
                raise InputError(f"depth PNG must be 16-bit single-channel, got {im.dtype} {im.shape}.", p)
            if im.shape != (H, W):
                raise InputError(f"depth PNG is {im.shape[1]}x{im.shape[0]}, the clip is {W}x{H}.", p)
            imgs.append(im)
        d = np.stack(imgs).astype(np.float32) * scale
        valid = d > 0
        if valid.any():
            d[~valid] = np.median(d[valid])
    elif path.is_file():
        d = _npy(path).astype(np.float32)
    else:
        raise InputError("precomputed depth not found.", path)
    _check(d, (F, H, W), path, "depth")
    if np.any(d <= 0):
        raise InputError("depth must be positive.", path)
    return d


def load_mask(path, shape):
    """Load a precomputed dynamic mask -> float32 [F,H,W] in [0,1]."""
    import cv2

    path = Path(path)
    F, H, W = shape
    if path.is_dir():
        ims = []
        for p in _pngs(path, F):
            im = _read_png(p, cv2.IMREAD_GRAYSCALE)
            if im.shape != (H, W):
                raise InputError(f"mask PNG is {im.shape[1]}x{im.shape[0]}, the clip is {W}x{H}.", p)
            ims.append(im)
        m = np.stack(ims).astype(np.float32) / 255.0
    elif path.is_file():
        m = _npy(path).astype(np.float32)
    else:
        raise InputError("precomputed mask not found.", path)
    _check(m, (F, H, W), path, "mask")
    if m.min() < 0 or m.max() > 1:
        raise InputError("mask values must lie in [0, 1].", path)
    return m


def load_tracks(path, num_frames):
    """Load precomputed tracks (.npz) -> :class:`Tracks`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("precomputed tracks not found.", path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"could not read ({exc}).", path) from exc
    for key in ("xy", "visible"):
        if key not in data:
            raise InputError(f"missing array {key!r}.", path, "Save xy [P,F,2] and visible [P,F].")
    xy, vis = data["xy"].astype(np.float32), data["visible"].astype(bool)
    if xy.ndim != 3 or xy.shape[1:] != (num_frames, 2):
        raise InputError(f"xy has shape {xy.shape}, expected [P,{num_frames},2].", path)
    if vis.shape != xy.shape[:2]:
        raise InputError(f"visible has shape {vis.shape}, expected {xy.shape[:2]}.", path)
    if not np.all(np.isfinite(xy)):
        raise InputError("xy contains NaN or infinite values.", path)
    conf = data.get("confidence", vis.astype(np.float32)).astype(np.float32)
    if conf.shape != vis.shape:
        raise InputError(f"confidence has shape {conf.shape}, expected {vis.shape}.", path)
    qf = data.get("query_frame", np.argmax(vis, axis=1)).astype(np.int64)
    return Tracks(xy, vis, conf, qf)
