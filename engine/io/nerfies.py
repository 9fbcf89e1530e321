"""Nerfies / HyperNeRF dataset reader.

Layout::

    dataset.json    {"ids": [...], "train_ids": [...], "val_ids": [...]}
    metadata.json   {id: {"warp_id", "time_id"?, "camera_id", "appearance_id"}}
    camera/<id>.json  orientation (3x3 world-to-camera rows), position (centre),
                      focal_length, pixel_aspect_ratio, principal_point, skew,
                      radial_distortion [k1,k2,k3], tangential_distortion [p1,p2], image_size [W,H]
    rgb/{1x,2x,4x,...}/<id>.png
    scene.json      {"scale", "center", "near", "far"}   (optional)

Conventions. Nerfies' camera model (``nerfies/camera.py``) generates rays at pixel centres
``arange(W) + 0.5`` and maps pixel ``p`` to ``(p - principal_point) / focal_length``, so its
principal point already uses our continuous convention: no shift. Its camera axes are
OpenCV's (x right, y down, z forward), and its distortion polynomial matches OpenCV's,
so ``dist = (k1, k2, p1, p2, k3)``. ``fy = focal_length * pixel_aspect_ratio``, ``K[0,1] = skew``.

Like Nerfies' loader, positions are mapped into the normalised scene:
``position' = (position - scene.center) * scene.scale`` (rotations unchanged); near/far are
taken from ``scene.json`` as they are (already in the normalised scene). ``scale=s`` (the
rgb folder ``{s}x``) divides the image size (rounded) and multiplies focal length,
principal point and skew by ``1/s``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .clip import Clip, FrameSource, finalize, load_json, normalise_times


def _arr(cam: dict, key: str, shape, path: Path, default=None) -> np.ndarray:
    if key not in cam:
        if default is not None:
            return np.asarray(default, dtype=np.float64)
        raise InputError(f"camera is missing '{key}'.", path, "Re-export the Nerfies camera file.")
    try:
        a = np.asarray(cam[key], dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != tuple(shape):
        raise InputError(f"camera field '{key}' should have shape {tuple(shape)}.", path,
                         "Re-export the Nerfies camera file.")
    if not np.isfinite(a).all():
        raise InputError(f"camera field '{key}' has NaN or infinite values.", path, "Re-export the Nerfies camera file.")
    return a


def read_nerfies_camera(path: Path, factor: float = 1.0):
    """One Nerfies camera file → ``(K [3,3], w2c [4,4], dist [5], (W, H))`` (unnormalised)."""
    cam = load_json(path)
    if not isinstance(cam, dict):
        raise InputError("camera file is not a JSON object.", path, "Re-export the Nerfies camera file.")
    R = _arr(cam, "orientation", (3, 3), path)
    C = _arr(cam, "position", (3,), path)
    f = float(_arr(cam, "focal_length", (), path))
    par = float(_arr(cam, "pixel_aspect_ratio", (), path, 1.0))
    pp = _arr(cam, "principal_point", (2,), path)
    skew = float(_arr(cam, "skew", (), path, 0.0))
    rad = _arr(cam, "radial_distortion", (3,), path, [0.0, 0.0, 0.0])
    tan = _arr(cam, "tangential_distortion", (2,), path, [0.0, 0.0])
    size = _arr(cam, "image_size", (2,), path)
    s = 1.0 / factor
    K = np.array([[f * s, skew * s, pp[0] * s], [0.0, f * par * s, pp[1] * s], [0, 0, 1.0]])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ C
    dist = np.array([rad[0], rad[1], tan[0], tan[1], rad[2]])
    W, H = int(round(size[0] * s)), int(round(size[1] * s))
    return K, w2c, dist, (W, H)


def is_nerfies(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / "dataset.json").is_file() and (path / "camera").is_dir()


def load_nerfies(path, scale: int = 1, fps: float = 0.0, apply_scene: bool = True) -> Clip:
    """Read a Nerfies/HyperNeRF capture (vrig or interp split from ``dataset.json``).

    Parameters
    ----------
    path : path
        Dataset folder.
    scale : int
        Image downscale factor; picks ``rgb/{scale}x``.
    fps : float
        Frame rate to record (the dataset has none; ``0`` = unknown).
    apply_scene : bool
        Apply ``scene.json`` centre/scale to camera positions.

    Returns
    -------
    Clip
        Frames ordered as ``dataset.json['ids']`` (or train then val ids), sorted by time;
        ``split['train'|'val']`` from ``train_ids``/``val_ids``.
    """
    root = Path(path)
    ds_path = root / "dataset.json"
    ds = load_json(ds_path)
    if not isinstance(ds, dict) or "train_ids" not in ds:
        raise InputError("dataset.json has no 'train_ids'.", ds_path, "Use a Nerfies/HyperNeRF dataset.json.")
    for key in ("train_ids", "val_ids", "ids"):
        if key in ds and not (isinstance(ds[key], list) and all(isinstance(i, (str, int)) for i in ds[key])):
            raise InputError(f"'{key}' must be a list of item ids, got {type(ds[key]).__name__}.", ds_path,
                             "Fix dataset.json.")
    train_ids = [str(i) for i in ds["train_ids"]]
    val_ids = [str(i) for i in ds.get("val_ids", [])]
    ids = [str(i) for i in ds.get("ids", train_ids + val_ids)]
    for i in train_ids + val_ids:
        if i not in ids:
            ids.append(i)
    meta_path = root / "metadata.json"
    meta = load_json(meta_path) if meta_path.is_file() else {}
    if not isinstance(meta, dict) or not all(isinstance(v, dict) for v in meta.values()):
        raise InputError("metadata.json must be an object mapping item ids to objects.", meta_path,
                         "Fix metadata.json (Nerfies layout).")
    raw_t = []
    for i in ids:
        m = meta.get(i)
        if meta and m is None:
            raise InputError(f"no metadata for item '{i}'.", meta_path, "Add the item or remove it from dataset.json.")
        if m is None:
            raw_t.append(float(len(raw_t)))
        else:
            key = "time_id" if "time_id" in m else "warp_id"
            if key not in m:
                raise InputError(f"item '{i}' has neither time_id nor warp_id.", meta_path,
                                 "Add time_id/warp_id to each item.")
            if not isinstance(m[key], (int, float)) or isinstance(m[key], bool) or not np.isfinite(m[key]):
                raise InputError(f"item '{i}' {key} must be a number, got {m[key]!r}.", meta_path, "Fix metadata.json.")
            raw_t.append(float(m[key]))
    order = np.argsort(np.asarray(raw_t), kind="stable")
    ids = [ids[k] for k in order]
    times = normalise_times(np.asarray(raw_t)[order])

    rgb = root / "rgb" / f"{int(scale)}x"
    if not rgb.is_dir():
        raise InputError(f"image folder rgb/{int(scale)}x is missing.", rgb,
                         f"Pick a scale that exists under {root / 'rgb'}.")
    paths, Ks, w2cs, dists, size = [], [], [], [], None
    for i in ids:
        cpath = root / "camera" / f"{i}.json"
        K, w2c, dist, sz = read_nerfies_camera(cpath, float(scale))
        if size is None:
            size = sz
        elif sz != size:
            raise InputError(f"image_size {sz} differs from the first camera's {size}.", cpath,
                             "All frames must share one image size.")
        p = rgb / f"{i}.png"
        if not p.is_file():
            alt = [q for q in (rgb / f"{i}.jpg", rgb / f"{i}.jpeg") if q.is_file()]
            if not alt:
                raise InputError(f"image for item '{i}' is missing.", p, "Restore the image or pick another scale.")
            p = alt[0]
        paths.append(p)
        Ks.append(K), w2cs.append(w2c), dists.append(dist)
    K, w2c, dist = np.stack(Ks), np.stack(w2cs), np.stack(dists)
    near = far = None
    center = None
    sscale = None
    scene_path = root / "scene.json"
    if scene_path.is_file():
        sc = load_json(scene_path)
        if not isinstance(sc, dict):
            raise InputError("scene.json must be a JSON object.", scene_path, "Fix scene.json.")
        try:
            c = np.asarray(sc.get("center", [0, 0, 0]), dtype=np.float64).reshape(3)
            s = float(sc.get("scale", 1.0))
            near, far = sc.get("near"), sc.get("far")
        except (AttributeError, TypeError, ValueError):
            raise InputError("scene.json needs numeric 'center' [3] and 'scale'.", scene_path,
                             "Fix scene.json.") from None
        if not np.isfinite(c).all() or not np.isfinite(s) or s <= 0:
            raise InputError("scene.json has a non-finite centre or non-positive scale.", scene_path, "Fix scene.json.")
        if apply_scene:
            R = w2c[:, :3, :3]
            C = -np.einsum("fji,fj->fi", R, w2c[:, :3, 3])
            C = (C - c) * s
            w2c[:, :3, 3] = -np.einsum("fij,fj->fi", R, C)
    pos = {i: k for k, i in enumerate(ids)}
    split = {"train": sorted(pos[i] for i in train_ids), "val": sorted(pos[i] for i in val_ids)}
    clip = Clip(frames=FrameSource(paths=paths), width=size[0], height=size[1], fps=float(fps), times=times,
                frame_ids=ids, K=K, w2c=w2c, dist=dist, split=split, source=root,
                near=None if near is None else float(near), far=None if far is None else float(far))
    clip.validate_cameras()
    first = clip.frames.load(0)
    if first.shape[:2] != (clip.height, clip.width):
        raise InputError(f"image is {first.shape[1]}x{first.shape[0]} but the camera says "
                         f"{clip.width}x{clip.height}.", paths[0], "Check the rgb scale folder matches the cameras.")
    return finalize(clip)
