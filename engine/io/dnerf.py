"""D-NeRF / Blender-NeRF reader (``transforms_{train,val,test}.json``).

Each file has ``camera_angle_x`` (horizontal FOV, radians) and ``frames[]`` with
``file_path`` (relative to the folder, with or without extension), ``transform_matrix``
(camera-to-world, OpenGL/Blender axes: x right, y up, looking down −z) and ``time``
(in ``[0,1]``; missing times come from frame order). Instant-NGP style ``fl_x``/``fl_y``/
``cx``/``cy``/``w``/``h`` are used when present. Otherwise ``fx = fy = W / (2 tan(angle/2))``
and ``cx = W/2, cy = H/2`` (centred in our continuous convention).

Conversion: ``c2w_cv = c2w_gl · diag(1, −1, −1, 1)``, ``w2c = inverse(c2w_cv)``.
Frames are train, then val, then test (file order within each); ``split`` names them.
Times are used as given (D-NeRF's are already in ``[0, 1]``), clipped to ``[0, 1]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .clip import IMAGE_EXTS, Clip, FrameSource, finalize, image_size, load_json, times_from_count

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def is_dnerf(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test"))


def _resolve(root: Path, fp: str, jpath: Path) -> Path:
    p = (root / fp).resolve() if not Path(fp).is_absolute() else Path(fp)
    if p.suffix.lower() in IMAGE_EXTS and p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg"):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    raise InputError(f"image '{fp}' is missing.", jpath, "Check file_path entries point at existing images.")


def _check_numbers(obj: dict, keys, jpath: Path, where: str) -> None:
    """Refuse a present key whose value is not a finite number (a string, a list, NaN)."""
    for key in keys:
        v = obj.get(key)
        if key in obj and (not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v)):
            raise InputError(f"{where}'{key}' must be a finite number, got {v!r}.", jpath, "Fix the value.")


def load_dnerf(path, fps: float = 0.0, scale: int = 1) -> Clip:
    """Read a D-NeRF/Blender-NeRF folder.

    Parameters
    ----------
    path : path
        Folder with ``transforms_*.json``.
    fps : float
        Frame rate to record (``0`` = unknown).
    scale : int
        Load frames downscaled by this integer factor (``Clip.downscale``); ``K`` stays full-res.
    """
    root = Path(path)
    paths, c2ws, times, ids, split, Ks = [], [], [], [], {}, []
    size = None
    for name in ("train", "val", "test"):
        jpath = root / f"transforms_{name}.json"
        if not jpath.is_file():
            continue
        js = load_json(jpath)
        if not isinstance(js, dict) or not isinstance(js.get("frames"), list):
            raise InputError("no 'frames' list.", jpath, "Use a D-NeRF/Blender-NeRF transforms file.")
        if "camera_angle_x" not in js and "fl_x" not in js:
            raise InputError("no 'camera_angle_x' (or 'fl_x').", jpath, "Add the camera field of view.")
        _check_numbers(js, ("camera_angle_x", "fl_x", "fl_y", "cx", "cy"), jpath, "")
        for key in ("w", "h"):
            if key in js and (not isinstance(js[key], int) or isinstance(js[key], bool) or js[key] <= 0):
                raise InputError(f"'{key}' must be a positive integer (pixels), got {js[key]!r}.", jpath, "Fix it.")
        split[name] = []
        for k, fr in enumerate(js["frames"]):
            try:
                M = np.asarray(fr["transform_matrix"], dtype=np.float64)
                fp = str(fr["file_path"])
            except (KeyError, TypeError, ValueError):
                raise InputError(f"frame {k} needs 'file_path' and a numeric 'transform_matrix'.", jpath,
                                 "Fix the frame entry.") from None
            if M.shape == (3, 4):
                M = np.vstack([M, [0, 0, 0, 1.0]])
            if M.shape != (4, 4):
                raise InputError(f"frame {k} transform_matrix has shape {M.shape}; expected 4x4.", jpath,
                                 "Fix the frame entry.")
            if not isinstance(fr, dict):
                raise InputError(f"frame {k} is not an object.", jpath, "Fix the frame entry.")
            _check_numbers(fr, ("time",), jpath, f"frame {k} ")
            img = _resolve(root, fp, jpath)
            if size is None:
                size = image_size(img)
            W, H = js.get("w", size[0]), js.get("h", size[1])
            if (int(W), int(H)) != size:
                raise InputError(f"w/h {W}x{H} differ from the images' {size[0]}x{size[1]}.", jpath, "Fix w/h.")
            if "fl_x" in js:
                fx = float(js["fl_x"])
                fy = float(js.get("fl_y", fx))
            else:
                ang = float(js["camera_angle_x"])
                fx = fy = 0.5 * W / np.tan(0.5 * ang) if 0 < ang < np.pi else float("nan")
                if not np.isfinite(fx):
                    raise InputError(f"camera_angle_x={ang} is not in (0, pi).", jpath, "Give the FOV in radians.")
            cx, cy = float(js.get("cx", W / 2)), float(js.get("cy", H / 2))
            Ks.append(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]))
            split[name].append(len(paths))
            paths.append(img)
            c2ws.append(M)
            times.append(float(fr["time"]) if "time" in fr else np.nan)
            ids.append(fp)
    if not paths:
        raise InputError("no frames in transforms_*.json.", root, "Add frames to transforms_train.json.")
    c2w = np.stack(c2ws)
    if not np.isfinite(c2w).all():
        raise InputError("a transform_matrix has NaN/inf values.", root / "transforms_train.json", "Fix the poses.")
    c2w_cv = c2w @ GL_TO_CV
    det = np.linalg.det(c2w_cv[:, :3, :3])
    if (np.abs(det) < 1e-9).any():
        raise InputError(f"frame {int(np.argmax(np.abs(det) < 1e-9))} has a singular transform_matrix.",
                         root, "Fix the poses.")
    w2c = np.linalg.inv(c2w_cv)
    w2c[:, 3] = [0, 0, 0, 1.0]
    t = np.asarray(times)
    if np.isnan(t).any():
        t = times_from_count(len(t))
    clip = Clip(frames=FrameSource(paths=paths), width=size[0], height=size[1], fps=float(fps),
                times=np.clip(t, 0.0, 1.0), frame_ids=ids, K=np.stack(Ks), w2c=w2c, dist=None,
                split={"train": split.get("train", []), "val": split.get("val", []), "test": split.get("test", [])},
                source=root, downscale=int(scale))
    return finalize(clip)
