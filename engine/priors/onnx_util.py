"""Shared helpers for the ONNX backends: session loading, sidecar JSON, input layout.

A model is given by path. Optional sidecar ``<model>.json`` (next to the ``.onnx`` file,
e.g. ``dinov2.onnx.json`` or ``dinov2.json``) overrides what is read from the graph:
``input_size`` ([H, W] or int), ``layout`` ("NCHW"|"NHWC"), ``mean``/``std`` (3 floats,
applied to RGB in [0,1]), ``patch_size`` (ViT), ``output`` ("inverse"|"depth"),
``background_class``/``foreground_classes`` (segmenters), ``size_multiple`` and ``input_width``
(models with dynamic H, W: the frame's aspect at ``input_width`` px, both sides rounded to a
multiple of ``size_multiple``; see :func:`dynamic_input_size`). The same settings can be given
without a file beside the model (a model in a read-only folder): :func:`model_settings` lays
them over the sidecar's, :func:`parse_settings` reads them from a command line.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def load_session(model_path):
    """Open an onnxruntime CPU session; raise :class:`InputError` naming the file on failure."""
    if model_path is None:
        raise InputError("backend 'onnx' needs a model path.", fix="Pass model_path=... or use the weight-free backend.")
    path = Path(model_path)
    if not path.is_file():
        raise InputError("ONNX model not found.", path, "Check the model path in the prior settings.")
    try:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - any load failure is bad input
        raise InputError(f"could not load ONNX model ({exc}).", path, "Export the model again with opset >= 13.") from exc


def read_sidecar(model_path) -> dict:
    """Return the sidecar JSON dict for ``model_path`` (``{}`` when none exists)."""
    path = Path(model_path)
    for cand in (Path(str(path) + ".json"), path.with_suffix(".json")):
        if cand.is_file():
            try:
                data = json.loads(cand.read_text())
            except ValueError as exc:
                raise InputError(f"sidecar JSON is not valid ({exc}).", cand) from exc
            if not isinstance(data, dict):
                raise InputError("sidecar JSON must be an object.", cand)
            return data
    return {}


#: the sidecar keys the priors read (model_settings refuses others: a typo would be ignored silently)
SETTING_KEYS = ("input_size", "layout", "mean", "std", "patch_size", "output", "background_class",
                "foreground_classes", "size_multiple", "input_width")


def model_settings(model_path, given: dict | None = None) -> dict:
    """The model's sidecar (:func:`read_sidecar`) with ``given`` laid over it, key by key."""
    side = dict(read_sidecar(model_path))
    if given:
        unknown = sorted(set(given) - set(SETTING_KEYS))
        if unknown:
            raise InputError(f"unknown model setting(s) {', '.join(unknown)}.", model_path,
                             f"Use only {', '.join(SETTING_KEYS)}.")
        side.update(given)
    return side


def parse_settings(text: str, option: str = "--depth-sidecar") -> dict:
    """Model settings from a command line: a JSON object, or the path of a JSON file holding one."""
    path = Path(text)
    source = None
    if not text.lstrip().startswith("{") and path.is_file():
        source, text = path, path.read_text()
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise InputError(f"{option} is not valid JSON ({exc}).", source,
                         'Give a JSON object such as \'{"size_multiple": 64}\' or the path of a file holding one.') from exc
    if not isinstance(data, dict):
        raise InputError(f"{option} must be a JSON object.", source, 'Give e.g. \'{"size_multiple": 64}\'.')
    unknown = sorted(set(data) - set(SETTING_KEYS))
    if unknown:
        raise InputError(f"{option}: unknown setting(s) {', '.join(unknown)}.", source,
                         f"Use only {', '.join(SETTING_KEYS)}.")
    return data


def image_input_spec(session, sidecar: dict, default_size=(224, 224)):
    """Work out (name, layout, (H, W), batch_fixed) of a model's single image input.

    Layout: sidecar ``layout`` if given, else NHWC when the last dim is 3, else NCHW.
    Size: sidecar ``input_size`` if given, else the static dims of the graph, else ``default_size``.
    """
    inp = session.get_inputs()[0]
    shape = list(inp.shape)
    layout = sidecar.get("layout")
    if layout is None:
        layout = "NHWC" if len(shape) == 4 and shape[-1] == 3 and shape[1] != 3 else "NCHW"
    layout = layout.upper()
    if layout not in ("NCHW", "NHWC"):
        raise InputError(f"unsupported layout {layout!r}.", fix="Use NCHW or NHWC in the sidecar JSON.")
    size = sidecar.get("input_size")
    if size is not None:
        size = (int(size), int(size)) if np.isscalar(size) else (int(size[0]), int(size[1]))
    else:
        hw = shape[2:4] if layout == "NCHW" else shape[1:3]
        if all(isinstance(d, int) and d > 0 for d in hw):
            size = (int(hw[0]), int(hw[1]))
        else:
            size = tuple(default_size)
    batch_fixed = isinstance(shape[0], int) and shape[0] > 0
    return inp.name, layout, size, batch_fixed


def prepare_images(frames: np.ndarray, size, layout: str, mean, std) -> np.ndarray:
    """Resize uint8 RGB ``frames [B,H,W,3]`` to ``size`` (H, W) and normalise.

    Returns float32 ``[B,3,h,w]`` (NCHW) or ``[B,h,w,3]`` (NHWC):
    ``(rgb/255 - mean) / std``.
    """
    import cv2

    h, w = size
    out = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA if f.shape[0] > h else cv2.INTER_LINEAR)
                    for f in frames]).astype(np.float32) / 255.0
    out = (out - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    if layout == "NCHW":
        out = out.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(out, dtype=np.float32)


def has_dynamic_hw(session, layout: str) -> bool:
    """True when the image input's H or W is not a fixed positive integer in the graph."""
    shape = list(session.get_inputs()[0].shape)
    hw = shape[2:4] if layout == "NCHW" else shape[1:3]
    return not all(isinstance(d, int) and d > 0 for d in hw)


def dynamic_input_size(H: int, W: int, width: int, multiple: int = 32):
    """``(h, w)`` for a model with dynamic input size: the frame's aspect ``H:W`` at about
    ``width`` px wide, each side rounded to the nearest multiple of ``multiple`` (at least one)."""
    m = max(1, int(multiple))
    w = max(m, int(round(float(width) / m)) * m)
    h = max(m, int(round(float(width) * H / W / m)) * m)
    return h, w
