"""Clip manifest (``format: "motion-splats-clip"``, version 1): reader, validator, writer.

See ``docs/clip_manifest.md`` for the format. Paths inside are relative to the manifest.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..fsutil import atomic_write_json
from .clip import IMAGE_EXTS, VIDEO_EXTS, Clip, FrameSource, finalize, load_json

FORMAT = "motion-splats-clip"
VERSION = 1
_FIX = "Re-export the clip from Blender (Motion Splats > Export Clip)."


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def validate_manifest(m, path) -> None:
    """Check a parsed manifest against the version-1 schema; raise :class:`InputError` naming ``path``."""
    def bad(msg):
        raise InputError(msg, path, _FIX)

    if not isinstance(m, dict):
        bad("manifest is not a JSON object.")
    if m.get("format") != FORMAT:
        bad(f"'format' is {m.get('format')!r}, expected {FORMAT!r}.")
    if m.get("version") != VERSION:
        bad(f"unsupported version {m.get('version')!r} (this engine reads {VERSION}).")
    video, frames = m.get("video"), m.get("frames")
    if (video is None) == (frames is None):
        bad("exactly one of 'video' and 'frames' must be given.")
    if video is not None and not isinstance(video, str):
        bad("'video' must be a path string or null.")
    if frames is not None and (not isinstance(frames, list) or not frames or
                               not all(isinstance(f, str) for f in frames)):
        bad("'frames' must be a non-empty list of path strings or null.")
    for k in ("frame_start", "frame_end", "width", "height"):
        if not isinstance(m.get(k), int) or isinstance(m.get(k), bool):
            bad(f"'{k}' must be an integer.")
    if m["width"] <= 0 or m["height"] <= 0:
        bad("'width' and 'height' must be positive.")
    if m["frame_end"] < m["frame_start"]:
        bad("'frame_end' is before 'frame_start'.")
    if not _num(m.get("fps")) or m["fps"] <= 0:
        bad("'fps' must be a positive number.")
    n = m["frame_end"] - m["frame_start"] + 1
    if frames is not None and len(frames) != n:
        bad(f"{len(frames)} frame paths for frames {m['frame_start']}..{m['frame_end']} ({n}).")
    t = m.get("time", {"frame_start": m["frame_start"], "frame_end": m["frame_end"]})
    if not isinstance(t, dict) or not all(_num(t.get(k)) for k in ("frame_start", "frame_end")):
        bad("'time' must be {'frame_start': number, 'frame_end': number}.")
    cams = m.get("cameras")
    if cams is not None:
        if not isinstance(cams, list):
            bad("'cameras' must be a list or null.")
        seen = set()
        for i, c in enumerate(cams):
            if not isinstance(c, dict) or not isinstance(c.get("frame"), int):
                bad(f"camera {i} needs an integer 'frame'.")
            if not (m["frame_start"] <= c["frame"] <= m["frame_end"]):
                bad(f"camera {i} frame {c['frame']} is outside {m['frame_start']}..{m['frame_end']}.")
            if c["frame"] in seen:
                bad(f"camera {i} repeats frame {c['frame']}.")
            seen.add(c["frame"])
            for key, shape in (("K", (3, 3)), ("w2c", (4, 4))):
                try:
                    a = np.asarray(c.get(key), dtype=np.float64)
                except (TypeError, ValueError):
                    a = np.zeros(0)
                if a.shape != shape:
                    bad(f"camera {i} '{key}' must be a {shape[0]}x{shape[1]} array of numbers.")
            d = c.get("dist")
            if d is not None:
                try:
                    a = np.asarray(d, dtype=np.float64)
                except (TypeError, ValueError):
                    a = np.zeros(0)
                if a.shape != (5,):
                    bad(f"camera {i} 'dist' must be [k1,k2,p1,p2,k3] or null.")
        if cams and len(seen) != n:
            bad(f"{len(seen)} cameras for {n} frames; give one per frame or none.")
    for k in ("masks_dir",):
        if m.get(k) is not None and not isinstance(m[k], str):
            bad(f"'{k}' must be a path string.")
    if m.get("priors") is not None and (not isinstance(m["priors"], dict) or
                                        not all(isinstance(v, str) for v in m["priors"].values())):
        bad("'priors' must map names to path strings.")
    unknown = sorted(set(m.get("priors") or {}) - set(PRIOR_NAMES))
    if unknown:
        bad(f"'priors' has unknown name(s) {unknown}; known: {list(PRIOR_NAMES)}.")


#: prior names a manifest may give (``priors``), as ``train``'s --depth-path/--mask-path/--tracks-path
PRIOR_NAMES = ("depth", "mask", "tracks")
PRIOR_EXTS = (".npy", ".npz", "")  # "" = a folder of PNGs


def media_path(base: Path, rel: str, exts, what: str, manifest: Path) -> Path:
    """``base / rel``, refused unless it stays inside the manifest's folder or is a file of
    the expected kind (``exts``; ``None`` = inside only).

    A manifest is data: it must not make the engine open arbitrary files on the machine
    (``"frames": ["../../etc/passwd"]``). Footage kept elsewhere (a video on another disk)
    is fine, as long as it is footage.
    """
    p = (base / rel).resolve()
    inside = p == base.resolve() or base.resolve() in p.parents
    if inside or (exts is not None and p.suffix.lower() in exts and p.suffix):
        return p
    kinds = "" if exts is None else f" or be a {'/'.join(e for e in exts if e)} file"
    raise InputError(f"'{what}' path {rel!r} is outside the manifest's folder; it must stay inside{kinds}.",
                     manifest, "Re-export the clip from Blender, or fix the path.")


def is_manifest(path: Path) -> bool:
    path = Path(path)
    if not (path.is_file() and path.suffix.lower() == ".json"):
        return False
    try:
        head = path.read_text(encoding="utf-8", errors="replace")[:4096]
    except OSError:
        return False
    return FORMAT in head


def load_manifest(path, scale: int = 1) -> Clip:
    """Read a clip manifest → :class:`Clip` (cameras if the manifest has them).

    Engine time of Blender frame ``f`` is ``(f - time.frame_start) / (time.frame_end - time.frame_start)``.
    """
    path = Path(path)
    m = load_json(path)
    validate_manifest(m, path)
    base = path.parent
    fs, fe = m["frame_start"], m["frame_end"]
    if m["frames"] is None:  # bound the frame range by the video before building any per-frame list
        from .video import video_info

        vpath = media_path(base, m["video"], VIDEO_EXTS, "video", path)
        n = video_info(vpath)[0]
        if fe - fs + 1 > n:
            raise InputError(f"'frame_end' - 'frame_start' + 1 = {fe - fs + 1} frames but the video has {n}.", path,
                             "Fix frame_start/frame_end to the video's frame range.")
    blender_frames = list(range(fs, fe + 1))
    if m["frames"] is not None:
        paths = [media_path(base, p, IMAGE_EXTS, "frame", path) for p in m["frames"]]
        missing = [p for p in paths if not p.is_file()]
        if missing:
            raise InputError(f"{len(missing)} frame image(s) are missing, e.g. {missing[0]}.", path,
                             "Re-export the frames or fix the paths (relative to the manifest).")
        frames = FrameSource(paths=paths)
        frame_ids = [p.name for p in paths]
    else:
        # the video's first frame is frame_start
        frames = FrameSource(video=vpath, indices=list(range(fe - fs + 1)))
        frame_ids = [str(f) for f in blender_frames]
    t = m.get("time") or {"frame_start": fs, "frame_end": fe}
    span = float(t["frame_end"]) - float(t["frame_start"])
    times = (np.asarray(blender_frames, dtype=np.float64) - float(t["frame_start"])) / span if span > 0 \
        else np.zeros(len(blender_frames))
    K = w2c = dist = None
    cams = m.get("cameras") or []
    if cams:
        by = {c["frame"]: c for c in cams}
        K = np.array([by[f]["K"] for f in blender_frames], dtype=np.float64)
        w2c = np.array([by[f]["w2c"] for f in blender_frames], dtype=np.float64)
        if any(by[f].get("dist") is not None for f in blender_frames):
            dist = np.array([by[f].get("dist") or [0.0] * 5 for f in blender_frames], dtype=np.float64)
    masks = None
    if m.get("masks_dir"):
        from .clip import list_images

        md = media_path(base, m["masks_dir"], None, "masks_dir", path)
        if not md.is_dir():
            raise InputError("masks_dir does not exist.", md, "Re-export masks or remove masks_dir.")
        masks = list_images(md)
    clip = Clip(frames=frames, width=m["width"], height=m["height"], fps=float(m["fps"]), times=times,
                frame_ids=frame_ids, K=K, w2c=w2c, dist=dist, source=path, masks=masks,
                priors={k: media_path(base, v, PRIOR_EXTS, f"priors.{k}", path) for k, v in
                        (m.get("priors") or {}).items()}, downscale=int(scale),
                meta={"frame_start": fs, "frame_end": fe})
    return finalize(clip)


def write_manifest(path, *, width: int, height: int, fps: float, frame_start: int, frame_end: int,
                   video=None, frames=None, cameras=None, time=None, masks_dir=None, priors=None) -> dict:
    """Write a version-1 clip manifest atomically and return it.

    Paths (``video``, ``frames``, ``masks_dir``, ``priors`` values) may be absolute or
    relative; they are stored relative to the manifest's folder.

    Parameters
    ----------
    cameras : list of dict, optional
        ``{"frame": int, "K": [3,3], "w2c": [4,4] (OpenCV), "dist": [5] or None}``
        (arrays may be numpy).
    """
    path = Path(path)
    base = path.parent.resolve()

    def rel(p):
        return None if p is None else Path(os.path.relpath(Path(p).resolve() if Path(p).is_absolute()
                                                           else (base / p).resolve(), base)).as_posix()

    m = {"format": FORMAT, "version": VERSION, "video": rel(video),
         "frames": None if frames is None else [rel(f) for f in frames],
         "frame_start": int(frame_start), "frame_end": int(frame_end), "fps": float(fps),
         "width": int(width), "height": int(height),
         "cameras": [{"frame": int(c["frame"]), "K": np.asarray(c["K"], dtype=float).tolist(),
                      "w2c": np.asarray(c["w2c"], dtype=float).tolist(),
                      "dist": None if c.get("dist") is None else np.asarray(c["dist"], dtype=float).tolist()}
                     for c in (cameras or [])],
         "time": dict(time) if time else {"frame_start": int(frame_start), "frame_end": int(frame_end)}}
    if masks_dir is not None:
        m["masks_dir"] = rel(masks_dir)
    if priors:
        m["priors"] = {k: rel(v) for k, v in priors.items()}
    validate_manifest(m, path)
    atomic_write_json(path, m)
    return m
