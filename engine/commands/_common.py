"""Helpers shared by CLI commands: frame ranges, camera paths, devices."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError


def parse_frames(spec: str | None, frame_start: int, frame_end: int) -> list[int]:
    """``"all"``/None, ``"a-b"``, ``"a-b:step"`` or ``"1,5,9"`` -> sorted frame list."""
    if spec in (None, "", "all"):
        return list(range(frame_start, frame_end + 1))
    frames: set[int] = set()
    try:
        for part in spec.split(","):
            part = part.strip()
            step = 1
            if ":" in part:
                part, step_s = part.split(":")
                step = int(step_s)
            if "-" in part[1:]:
                a, b = part[0] + part[1:].split("-", 1)[0], part[1:].split("-", 1)[1]
                frames.update(range(int(a), int(b) + 1, step))
            else:
                frames.add(int(part))
    except ValueError:
        raise InputError(f"cannot parse frame list {spec!r}", None, "use e.g. 1-48, 1-48:4 or 1,12,24") from None
    return sorted(frames)


def load_camera_path(path: str | Path) -> list[dict]:
    """Read a camera path JSON (exported by the add-on) and validate it.

    Format: ``{"format": "motion-splats-camera-path", "version": 1, "cameras": [{"frame",
    "K" 3x3, "w2c" 4x4 (OpenCV axes), "width", "height"}]}``.
    """
    path = Path(path)
    fix = "export the camera path from Blender (Motion Splats › Export camera path)"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("camera path file not found", path, fix) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read camera path JSON ({exc})", path, fix) from None
    if not isinstance(data, dict) or data.get("format") != "motion-splats-camera-path":
        raise InputError("not a Motion Splats camera path ('format' must be 'motion-splats-camera-path')", path, fix)
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise InputError("'cameras' must be a non-empty list", path, fix)
    out = []
    for i, c in enumerate(cams):
        try:
            K = np.asarray(c["K"], dtype=np.float64)
            w2c = np.asarray(c["w2c"], dtype=np.float64)
            w, h, f = int(c["width"]), int(c["height"]), float(c["frame"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"camera {i} needs frame, K (3x3), w2c (4x4), width, height", path, fix) from None
        if K.shape != (3, 3) or w2c.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(w2c).all()):
            raise InputError(f"camera {i} has a malformed or non-finite K/w2c", path, fix)
        if abs(np.linalg.det(w2c[:3, :3]) - 1) > 1e-3 or w <= 0 or h <= 0:
            raise InputError(f"camera {i} has a non-rotation w2c or a bad image size", path, fix)
        out.append({"frame": f, "K": K, "w2c": w2c, "width": w, "height": h})
    return out


def pick_device(name: str = "auto"):
    """See :func:`engine.pipeline.pick_device` (imported lazily: it needs torch)."""
    from ..pipeline import pick_device as _pick

    return _pick(name)
