"""Helpers shared by CLI commands: frame ranges, camera paths, devices."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..bundle import camera_problem
from ..errors import InputError


#: most frames one command may be asked for (a day of footage at 60 fps is 5.2 million)
MAX_FRAMES = 100_000


def parse_frames(spec: str | None, frame_start: int, frame_end: int, option: str = "--frames") -> list[int]:
    """``"all"``/None, ``"a-b"``, ``"a-b:step"`` or ``"1,5,9"`` -> sorted frame list.

    Frames must lie in ``frame_start..frame_end`` (the bundle's range); a list of more
    than :data:`MAX_FRAMES` frames is refused before it is built.
    """
    if spec in (None, "", "all"):
        return list(range(frame_start, frame_end + 1))
    fix = f"use e.g. {frame_start}-{frame_end}, {frame_start}-{frame_end}:4 or {frame_start},{frame_end} " \
          f"(the bundle has frames {frame_start}..{frame_end})"
    frames: set[int] = set()
    try:
        for part in spec.split(","):
            part = part.strip()
            step = 1
            if ":" in part:
                part, step_s = part.split(":")
                step = int(step_s)
            if step < 1:
                raise ValueError
            if "-" in part[1:]:
                a, b = part[0] + part[1:].split("-", 1)[0], part[1:].split("-", 1)[1]
                lo, hi = int(a), int(b)
                if hi < lo or (hi - lo) // step + 1 + len(frames) > MAX_FRAMES:
                    raise InputError(f"{option} {spec!r} asks for {max(0, (hi - lo) // step + 1)} frames "
                                     f"(at most {MAX_FRAMES}, ranges low-high)", None, fix)
                frames.update(range(lo, hi + 1, step))
            else:
                frames.add(int(part))
    except ValueError:
        raise InputError(f"cannot parse {option} {spec!r}", None, fix) from None
    outside = [f for f in frames if not frame_start <= f <= frame_end]
    if outside:
        raise InputError(f"{option} {spec!r} includes frame {min(outside, key=lambda f: abs(f - frame_start))} "
                         f"outside the bundle's {frame_start}..{frame_end}", None, fix)
    return sorted(frames)


def load_camera_path(path: str | Path) -> list[dict]:
    """Read a camera path JSON (exported by the add-on) and validate it.

    Format: ``{"format": "motion-splats-camera-path", "version": 1, "cameras": [{"frame",
    "K" 3x3, "w2c" 4x4 (OpenCV axes), "width", "height"}]}``.
    """
    path = Path(path)
    fix = "export the camera path from Blender (Motion Splats › Export camera path)"
    try:
        if path.stat().st_size > 256 << 20:
            raise InputError("camera path file is larger than 256 MB", path, fix)
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
        if K.shape != (3, 3) or w2c.shape != (4, 4) or not np.isfinite(f):
            raise InputError(f"camera {i} has a malformed K/w2c or frame", path, fix)
        problem = camera_problem(K, w2c, w, h)
        if problem:
            raise InputError(f"camera {i} {problem}", path, fix)
        out.append({"frame": f, "K": K, "w2c": w2c, "width": w, "height": h})
    return out


def pick_device(name: str = "auto"):
    """See :func:`engine.pipeline.pick_device` (imported lazily: it needs torch)."""
    from ..pipeline import pick_device as _pick

    return _pick(name)
