"""COLMAP sparse model reader (``cameras/images/points3D`` in ``.bin`` or ``.txt``) via pycolmap.

Accepted layouts: ``<root>/sparse/0``, ``<root>/sparse`` or ``<root>`` itself holding the
model, with images in ``<root>/images`` (or ``image_dir=``). Frames are ordered by image
name; engine times are evenly spaced in that order. COLMAP's pixel convention is ours
(pixel centres at +0.5), so parameters are copied as they are:

============== ================================ =====================
model          params                           dist (k1,k2,p1,p2,k3)
============== ================================ =====================
SIMPLE_PINHOLE f, cx, cy                        None
PINHOLE        fx, fy, cx, cy                   None
SIMPLE_RADIAL  f, cx, cy, k                     (k, 0, 0, 0, 0)
RADIAL         f, cx, cy, k1, k2                (k1, k2, 0, 0, 0)
OPENCV         fx, fy, cx, cy, k1, k2, p1, p2   (k1, k2, p1, p2, 0)
============== ================================ =====================

Only registered images are frames; unregistered ones are left out.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .clip import Clip, FrameSource, finalize, times_from_count

_FILES = ("cameras", "images", "points3D")


def _has_model(d: Path) -> bool:
    return all((d / f"{f}.bin").is_file() for f in _FILES) or all((d / f"{f}.txt").is_file() for f in _FILES)


def find_model(root: Path) -> Path | None:
    for d in (root / "sparse" / "0", root / "sparse", root):
        if d.is_dir() and _has_model(d):
            return d
    return None


def is_colmap(path: Path) -> bool:
    return Path(path).is_dir() and find_model(Path(path)) is not None


def colmap_K_dist(model: str, params) -> tuple[np.ndarray, np.ndarray | None]:
    """COLMAP camera ``model`` name + ``params`` -> ``(K [3,3], dist [5] (k1,k2,p1,p2,k3) or None)``.

    Pure numpy (the add-on's COLMAP import in Blender uses it too); unsupported models
    raise ``ValueError(model)``.
    """
    p = np.asarray(params, dtype=np.float64)
    dist = None
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]; cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]; cx, cy = p[1], p[2]; dist = np.array([p[3], 0, 0, 0, 0.0])
    elif model == "RADIAL":
        fx = fy = p[0]; cx, cy = p[1], p[2]; dist = np.array([p[3], p[4], 0, 0, 0.0])
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]; dist = np.array([p[4], p[5], p[6], p[7], 0.0])
    else:
        raise ValueError(model)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), dist


def camera_to_K_dist(cam) -> tuple[np.ndarray, np.ndarray | None]:
    """pycolmap camera → ``(K [3,3], dist [5] or None)``; unsupported models raise ValueError."""
    name = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    return colmap_K_dist(name, cam.params)


def image_w2c(img) -> np.ndarray:
    """pycolmap image → ``w2c [4,4]``."""
    cfw = img.cam_from_world
    cfw = cfw() if callable(cfw) else cfw
    M = np.eye(4)
    M[:3, :4] = np.asarray(cfw.matrix(), dtype=np.float64)
    return M


def reconstruction_cameras(rec, names=None):
    """Per registered image (sorted by name): ``names, K [F,3,3], w2c [F,4,4], dist [F,5] or None, sizes``."""
    imgs = [im for im in rec.images.values() if (im.has_pose if not callable(im.has_pose) else im.has_pose())]
    imgs.sort(key=lambda im: im.name)
    Ks, w2cs, dists, sizes = [], [], [], []
    for im in imgs:
        cam = rec.cameras[im.camera_id]
        K, d = camera_to_K_dist(cam)
        Ks.append(K); dists.append(d); w2cs.append(image_w2c(im)); sizes.append((int(cam.width), int(cam.height)))
    any_d = any(d is not None for d in dists)
    dist = np.stack([np.zeros(5) if d is None else d for d in dists]) if any_d and imgs else None
    return [im.name for im in imgs], np.asarray(Ks).reshape(-1, 3, 3), np.asarray(w2cs).reshape(-1, 4, 4), dist, sizes


#: smallest record of each COLMAP binary file (bytes): camera id+model+w+h, image
#: id+qvec+tvec+camera+name NUL+point count, point id+xyz+rgb+error+track length
_MIN_RECORD = {"cameras.bin": 24, "images.bin": 73, "points3D.bin": 51}


def check_binary_counts(model: Path) -> None:
    """Refuse a binary model whose record count cannot fit in its file.

    Each ``.bin`` starts with a uint64 count; a truncated or forged header (4 bytes
    claiming 2^31 points) made pycolmap allocate tens of GB before failing.
    """
    for name, size in _MIN_RECORD.items():
        f = Path(model) / name
        if not f.is_file():
            continue
        n_bytes = f.stat().st_size
        head = f.read_bytes()[:8] if n_bytes >= 8 else b""
        count = int.from_bytes(head, "little") if head else -1
        if count < 0 or count * size > n_bytes - 8:
            raise InputError(f"{name} is truncated or corrupt: its header claims {max(count, 0)} records but the "
                             f"file has {n_bytes} bytes.", f, "Re-export the model from COLMAP.")


def load_colmap(path, image_dir=None, fps: float = 0.0, scale: int = 1) -> Clip:
    """Read a COLMAP sparse model and its images.

    Parameters
    ----------
    path : path
        Root folder (see module doc for layouts).
    image_dir : path, optional
        Image folder; default ``<root>/images``.
    fps : float
        Frame rate to record.
    scale : int
        Frame downscale factor for loading (``K`` stays full resolution).
    """
    import pycolmap

    root = Path(path)
    model = find_model(root)
    if model is None:
        raise InputError("no COLMAP model (cameras/images/points3D .bin or .txt).", root,
                         "Point at the folder with sparse/0 or the model files.")
    check_binary_counts(model)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as exc:  # pycolmap raises generic errors on corrupt files
        raise InputError(f"COLMAP model cannot be read ({exc}).", model, "Re-export the model from COLMAP.") from None
    try:
        names, K, w2c, dist, sizes = reconstruction_cameras(rec)
    except ValueError as exc:
        raise InputError(f"camera model {exc} is not supported.", model / "cameras.bin",
                         "Use PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV (undistort otherwise).") from None
    if not names:
        raise InputError("the model has no registered images.", model, "Re-run COLMAP mapping.")
    if len(set(sizes)) != 1:
        raise InputError(f"images have different camera sizes {sorted(set(sizes))}.", model,
                         "Use one image size for the whole clip.")
    imdir = Path(image_dir) if image_dir is not None else root / "images"
    paths = [imdir / n for n in names]
    for p in paths:
        if not p.is_file():
            raise InputError("image named in the COLMAP model is missing.", p, "Point image_dir at the images.")
    pts = rec.points3D
    if len(pts):
        xyz = np.array([p.xyz for p in pts.values()], dtype=np.float64)
        rgb = np.array([p.color for p in pts.values()], dtype=np.uint8)
    else:
        xyz = rgb = None
    W, H = sizes[0]
    clip = Clip(frames=FrameSource(paths=paths), width=W, height=H, fps=float(fps),
                times=times_from_count(len(names)), frame_ids=names, K=K, w2c=w2c, dist=dist,
                source=model, points=xyz, point_colors=rgb, downscale=int(scale))
    first = clip.frames.load(0)
    if first.shape[:2] != (H, W):
        raise InputError(f"image is {first.shape[1]}x{first.shape[0]} but its COLMAP camera is {W}x{H}.",
                         paths[0], "Use the images the model was built from.")
    return finalize(clip)
