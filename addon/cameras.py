# SPDX-License-Identifier: GPL-3.0-or-later
"""Camera import: Blender motion-tracking reconstructions and COLMAP models -> engine
cameras (``K [3,3]``, OpenCV ``w2c [4,4]``) -> an animated scene camera.

Design choice (issue #7): COLMAP models are parsed here in pure Python + numpy (text
``cameras.txt``/``images.txt`` and binary ``cameras.bin``/``images.bin``), not through
pycolmap (not available inside Blender) and not through an engine subprocess (the import
is a few milliseconds and must work before an engine interpreter is configured).

The pure functions (``parse_colmap_*``, ``colmap_K_dist``, ``tracking_K``) do not touch
``bpy`` and are unit-tested on arrays; :func:`build_animated_camera` (the one animated
camera builder, also used for result bundles) needs Blender. The axis conversion and
quaternion -> matrix are the engine's numpy ones (``engine.geometry.blender_camera``).

Conventions (docs/architecture.md): K in continuous pixels with y down (upper-left pixel
centre at (0.5, 0.5)), which is COLMAP's convention. Blender's tracking principal point
(``principal_point_pixels``) is measured with y *up* from the bottom edge of the frame
(marker space), so ``cy = H - py``.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..engine.errors import InputError
from ..engine.geometry.blender_camera import (blender_camera_from_intrinsics, blender_matrix_from_w2c,
                                              quat_to_matrix_np, w2c_from_blender_matrix)
from ..engine.io.colmap import colmap_K_dist as _engine_colmap_K_dist

#: COLMAP camera models: id -> (name, number of params)
COLMAP_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}


# -- math ---------------------------------------------------------------------------------
qvec_to_matrix = quat_to_matrix_np  # COLMAP's qvec is (w, x, y, z) like Blender's


def project(K, w2c, points) -> np.ndarray:
    """Pinhole projection of ``points [P,3]`` -> pixels ``[P,2]`` (no distortion)."""
    X = np.asarray(points, np.float64) @ np.asarray(w2c)[:3, :3].T + np.asarray(w2c)[:3, 3]
    uv = X @ np.asarray(K).T
    return uv[:, :2] / uv[:, 2:3]


# -- COLMAP -------------------------------------------------------------------------------
def colmap_K_dist(model: str, params) -> tuple[np.ndarray, np.ndarray | None]:
    """``(K [3,3], dist [5] or None)`` of a COLMAP camera; the engine's mapping, with the
    add-on's user-facing error for unsupported models."""
    try:
        return _engine_colmap_K_dist(model, params)
    except ValueError:
        raise InputError(f"COLMAP camera model {model} is not supported", None,
                         "undistort the model first (colmap image_undistorter) or use PINHOLE/OPENCV") from None


def find_colmap_model(folder) -> Path:
    """The folder holding ``cameras.txt``/``.bin`` + ``images.txt``/``.bin`` (``folder``, ``sparse/0``, ``sparse``)."""
    root = Path(folder)
    for d in (root, root / "sparse" / "0", root / "sparse", root / "0"):
        for ext in ("txt", "bin"):
            if (d / f"cameras.{ext}").is_file() and (d / f"images.{ext}").is_file():
                return d
    raise InputError("no COLMAP model (cameras.txt/.bin and images.txt/.bin) found", str(root),
                     "pick the model folder, e.g. sparse/0")


def _text_lines(path: Path):
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            yield line


def parse_colmap_text(model_dir) -> tuple[dict, list]:
    """``cameras {id: (model, width, height, params)}``, ``images [(name, qvec, tvec, camera_id)]``."""
    d = Path(model_dir)
    cameras = {}
    for line in _text_lines(d / "cameras.txt"):
        f = line.split()
        cameras[int(f[0])] = (f[1], int(f[2]), int(f[3]), [float(v) for v in f[4:]])
    images = []
    lines = list(_text_lines(d / "images.txt"))
    # images.txt: a pose line then a 2D-points line (which may be empty and then was skipped)
    i = 0
    while i < len(lines):
        f = lines[i].split()
        if len(f) >= 10 and not _looks_like_points(f):
            images.append((f[9], [float(v) for v in f[1:5]], [float(v) for v in f[5:8]], int(f[8])))
        i += 1
    return cameras, images


def _looks_like_points(f) -> bool:
    # a 2D-points line has a multiple of 3 numeric fields; a pose line ends with a file name
    try:
        float(f[-1])
        return True
    except ValueError:
        return False


def parse_colmap_binary(model_dir) -> tuple[dict, list]:
    """Same as :func:`parse_colmap_text` for ``cameras.bin`` / ``images.bin``."""
    d = Path(model_dir)
    cameras = {}
    with open(d / "cameras.bin", "rb") as fh:
        (n,) = struct.unpack("<Q", fh.read(8))
        for _ in range(n):
            cam_id, model_id, w, h = struct.unpack("<iiQQ", fh.read(24))
            name, nparams = COLMAP_MODELS.get(model_id, (f"MODEL_{model_id}", 0))
            if not nparams:
                raise InputError(f"unknown COLMAP camera model id {model_id}", str(d / "cameras.bin"), None)
            cameras[cam_id] = (name, int(w), int(h), list(struct.unpack(f"<{nparams}d", fh.read(8 * nparams))))
    images = []
    with open(d / "images.bin", "rb") as fh:
        (n,) = struct.unpack("<Q", fh.read(8))
        for _ in range(n):
            vals = struct.unpack("<i7di", fh.read(64))
            name = bytearray()
            while True:
                c = fh.read(1)
                if c in (b"\x00", b""):
                    break
                name += c
            (npts,) = struct.unpack("<Q", fh.read(8))
            fh.seek(24 * npts, 1)  # x, y (double) + point3D id (int64)
            images.append((name.decode("utf-8"), list(vals[1:5]), list(vals[5:8]), int(vals[8])))
    return cameras, images


def read_colmap_cameras(folder) -> dict:
    """Engine cameras of a COLMAP model, images sorted by name.

    Returns ``{"names", "K" [F,3,3], "w2c" [F,4,4], "dist" [F,5] or None, "width", "height"}``.
    """
    d = find_colmap_model(folder)
    try:
        cameras, images = parse_colmap_text(d) if (d / "images.txt").is_file() else parse_colmap_binary(d)
    except (OSError, ValueError, IndexError, struct.error) as exc:
        raise InputError(f"cannot read the COLMAP model ({type(exc).__name__}: {exc})", str(d),
                         "export it again from COLMAP (File > Export model as text)")
    if not images:
        raise InputError("the COLMAP model has no registered images", str(d), None)
    images.sort(key=lambda im: im[0])
    Ks, w2cs, dists, sizes = [], [], [], set()
    for name, q, t, cam_id in images:
        if cam_id not in cameras:
            raise InputError(f"image {name} refers to missing camera {cam_id}", str(d), None)
        model, w, h, params = cameras[cam_id]
        K, dist = colmap_K_dist(model, params)
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = qvec_to_matrix(q), t
        Ks.append(K); w2cs.append(w2c); dists.append(dist); sizes.add((w, h))
    if len(sizes) != 1:
        raise InputError("the COLMAP model mixes image sizes", str(d), "import one camera's images at a time")
    w, h = sizes.pop()
    dist = None if all(x is None for x in dists) else np.stack([np.zeros(5) if x is None else x for x in dists])
    return {"names": [im[0] for im in images], "K": np.stack(Ks), "w2c": np.stack(w2cs), "dist": dist,
            "width": int(w), "height": int(h)}


# -- Blender motion tracking ---------------------------------------------------------------
def tracking_K(focal_px: float, principal_px, width: int, height: int, pixel_aspect: float = 1.0) -> np.ndarray:
    """K of a Blender tracking camera (``focal_length_pixels``, ``principal_point_pixels`` with y up)."""
    fx = float(focal_px)
    fy = fx * float(pixel_aspect)
    return np.array([[fx, 0.0, float(principal_px[0])], [0.0, fy, float(height) - float(principal_px[1])],
                     [0.0, 0.0, 1.0]])


def tracking_dist(model: str, k1: float, k2: float, k3: float) -> np.ndarray | None:
    """OpenCV ``dist [5]`` of a tracking camera's POLYNOMIAL model (None when all zero).

    Blender's polynomial model is radial ``1 + k1 r² + k2 r⁴ + k3 r⁶`` on normalised
    coordinates, like OpenCV's. Other models (DIVISION, NUKE, BROWN) raise: undistort the
    footage in Blender first.
    """
    if model == "POLYNOMIAL":
        if k1 == k2 == k3 == 0.0:
            return None
        return np.array([k1, k2, 0.0, 0.0, k3])
    raise InputError(f"tracking distortion model {model} has no OpenCV equivalent", None,
                     "render undistorted footage (Movie Clip > Undistort) and set its coefficients to zero, "
                     "or use the Polynomial model")


def tracking_cameras(matrices, frames, K) -> dict:
    """Engine cameras from reconstructed camera matrices (Blender axes, camera-to-world, ``[F,4,4]``)."""
    mats = np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4)
    order = np.argsort(np.asarray(frames), kind="stable")
    w2c = np.stack([w2c_from_blender_matrix(mats[i]) for i in order]) if len(mats) else np.zeros((0, 4, 4))
    return {"frames": [int(frames[i]) for i in order], "K": np.repeat(np.asarray(K)[None], len(mats), 0),
            "w2c": w2c}


def read_tracking_reconstruction(clip) -> dict:
    """Engine cameras of a Movie Clip's camera solve (bpy). Frames are the clip's frames."""
    tracking = clip.tracking
    tcam = tracking.camera
    recon = tracking.objects.active.reconstruction if tracking.objects.active else tracking.reconstruction
    if not recon.is_valid or len(recon.cameras) == 0:
        raise InputError(f"movie clip '{clip.name}' has no camera solve", clip.filepath,
                         "track features and press Solve Camera Motion in the Movie Clip editor")
    w, h = int(clip.size[0]), int(clip.size[1])
    K = tracking_K(tcam.focal_length_pixels, tcam.principal_point_pixels, w, h, tcam.pixel_aspect)
    dist = tracking_dist(tcam.distortion_model, tcam.k1, tcam.k2, tcam.k3)
    n = len(recon.cameras)
    flat = np.zeros(n * 16, dtype=np.float32)
    recon.cameras.foreach_get("matrix", flat)
    # foreach_get on a matrix property yields column-major 4x4 blocks
    mats = flat.reshape(n, 4, 4).transpose(0, 2, 1).astype(np.float64)
    frames = np.zeros(n, dtype=np.int32)
    recon.cameras.foreach_get("frame", frames)
    out = tracking_cameras(mats, frames, K)
    # reconstruction frames are clip frames; scene frame = clip frame + clip.frame_start - 1
    out["frames"] = [f + int(clip.frame_start) - 1 for f in out["frames"]]
    out.update(width=w, height=h, dist=dist, average_error=float(recon.average_error))
    return out


# -- scene camera -------------------------------------------------------------------------
def build_animated_camera(scene, name: str, K, width: int, height: int, w2cs, frames, collection=None,
                          set_render: bool = True, make_scene_camera: bool = True):
    """An animated perspective camera (one linear key per frame) reproducing ``K`` and ``w2cs [F, 4, 4]``.

    The render size the intrinsics need is stored on the object (``ms_res_x`` ...) and,
    with ``set_render``, applied to the scene; ``make_scene_camera`` makes it the scene
    camera. Linear keys: no Bézier overshoot between per-frame poses. Returns the object.
    """
    import bpy
    import mathutils

    K = np.asarray(K, dtype=np.float64)
    s = blender_camera_from_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height))
    data = bpy.data.cameras.new(name)
    data.type = "PERSP"
    data.lens, data.sensor_width, data.sensor_height = s["lens"], s["sensor_width"], s["sensor_height"]
    data.sensor_fit = s["sensor_fit"]
    data.shift_x, data.shift_y = s["shift_x"], s["shift_y"]
    data.clip_start = 0.01
    obj = bpy.data.objects.new(name, data)
    (collection or scene.collection).objects.link(obj)
    obj["ms_res_x"], obj["ms_res_y"] = int(s["res_x"]), int(s["res_y"])
    obj["ms_pixel_aspect_x"], obj["ms_pixel_aspect_y"] = float(s["pixel_aspect_x"]), float(s["pixel_aspect_y"])
    if set_render:
        r = scene.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = s["res_x"], s["res_y"], 100
        r.pixel_aspect_x, r.pixel_aspect_y = s["pixel_aspect_x"], s["pixel_aspect_y"]
    obj.rotation_mode = "QUATERNION"
    w2cs = np.asarray(w2cs, dtype=np.float64).reshape(-1, 4, 4)
    prev = None
    for mw_np, f in zip(blender_matrix_from_w2c(w2cs), frames):
        loc, rot, _ = mathutils.Matrix(mw_np.tolist()).decompose()
        if prev is not None and prev.dot(rot) < 0:  # keep quaternion keys continuous
            rot.negate()
        prev = rot
        obj.location, obj.rotation_quaternion = loc, rot
        if len(w2cs) > 1:
            obj.keyframe_insert("location", frame=float(f))
            obj.keyframe_insert("rotation_quaternion", frame=float(f))
    if len(w2cs) > 1 and obj.animation_data and obj.animation_data.action:
        _linear_keys(obj)
        depth = float(np.median(np.abs(w2cs[:, 2, 3])))
        data.clip_end = max(100.0, 100 * depth)
    obj["ms_camera"] = True
    if make_scene_camera:
        scene.camera = obj
    return obj


def _linear_keys(obj) -> None:
    """Linear interpolation between the per-frame keys (no Bézier overshoot between frames)."""
    action = obj.animation_data.action
    curves = getattr(action, "fcurves", None)
    if curves is None:  # Blender 5 layered actions
        curves = []
        for layer in action.layers:
            for strip in layer.strips:
                for bag in strip.channelbags:
                    curves.extend(bag.fcurves)
    for fc in curves:
        for kp in fc.keyframe_points:
            kp.interpolation = "LINEAR"
