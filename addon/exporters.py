# SPDX-License-Identifier: GPL-3.0-or-later
"""Scene -> engine files: camera paths, clip manifests, edited node splines.

Every writer is atomic (temp file + ``os.replace``) and validates before it writes.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import bpy
import numpy as np

from . import build, fcurves
from ..engine import bundle as bundle_io
from ..engine.errors import InputError
from ..engine.fsutil import atomic_write_json
from ..engine.geometry.blender_camera import blender_camera_intrinsics

CAMERA_PATH_FORMAT = "motion-splats-camera-path"
CAMERA_PATH_VERSION = 1


def camera_K(scene, cam_obj) -> tuple[np.ndarray, int, int]:
    """Pinhole ``K [3, 3]`` and image size of ``cam_obj`` with the scene's render settings."""
    d, r = cam_obj.data, scene.render
    if d.type != "PERSP":
        raise InputError(f"camera '{cam_obj.name}' is {d.type}; only perspective cameras are supported", None,
                         "set the camera type to Perspective")
    fx, fy, cx, cy, w, h = blender_camera_intrinsics(
        d.lens, d.sensor_width, d.sensor_height, d.sensor_fit, d.shift_x, d.shift_y, r.resolution_x,
        r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y, r.resolution_percentage)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), int(w), int(h)


def sample_camera(scene, cam_obj, frames) -> list[dict]:
    """``{frame, K, w2c, width, height}`` per frame (the scene's current frame is kept)."""
    keep = (scene.frame_current, scene.frame_subframe)
    out = []
    try:
        for f in frames:  # one frame_set per frame: animated cameras / constraints evaluate
            f = float(f)
            scene.frame_set(int(np.floor(f)), subframe=f - np.floor(f))
            K, w, h = camera_K(scene, cam_obj)
            w2c = build.w2c_from_matrix_world(np.array(cam_obj.matrix_world))
            out.append({"frame": int(f) if f == int(f) else f, "K": K, "w2c": w2c, "width": w, "height": h})
    finally:
        scene.frame_set(keep[0], subframe=keep[1])
    return out


def write_camera_path(path, scene, cam_obj=None, frames=None) -> dict:
    """Write the camera path JSON the engine's ``render --camera`` reads; returns it."""
    cam_obj = cam_obj or scene.camera
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise InputError("the scene has no active camera", None, "set Scene > Camera")
    frames = range(scene.frame_start, scene.frame_end + 1) if frames is None else frames
    cams = sample_camera(scene, cam_obj, frames)
    for c in cams:
        if not np.isfinite(c["w2c"]).all() or abs(np.linalg.det(c["w2c"][:3, :3]) - 1) > 1e-3:
            raise InputError(f"camera at frame {c['frame']} has a degenerate transform", None,
                             "remove shear / zero scale from the camera and its parents")
    data = {"format": CAMERA_PATH_FORMAT, "version": CAMERA_PATH_VERSION, "camera": cam_obj.name,
            "fps": scene.render.fps / scene.render.fps_base,
            "cameras": [{"frame": c["frame"], "K": c["K"].tolist(), "w2c": c["w2c"].tolist(),
                         "width": c["width"], "height": c["height"]} for c in cams]}
    atomic_write_json(path, data)
    return data


def clip_frames(clip) -> tuple[str | None, list[str] | None]:
    """``(video, frames)`` of a Movie Clip: a movie file, or the files of an image sequence."""
    path = Path(bpy.path.abspath(clip.filepath))
    if clip.source == "MOVIE":
        return str(path), None
    # image sequence: the files in the folder with the same stem pattern and extension
    stem = re.sub(r"\d+$", "", path.stem)
    files = sorted(p for p in path.parent.iterdir()
                   if p.suffix.lower() == path.suffix.lower() and re.fullmatch(re.escape(stem) + r"\d+", p.stem))
    return None, [str(p) for p in files]


def write_clip_manifest(path, scene, clip, cam_obj=None, with_cameras: bool = True) -> dict:
    """Clip manifest (``docs/clip_manifest.md``) for Movie Clip ``clip`` and the scene camera.

    The clip's frames are the scene frames ``clip.frame_start ..`` (its duration); the
    cameras are sampled from ``cam_obj`` (default the scene camera) on those frames, with
    the render resolution set to the clip size.
    """
    from ..engine.io.manifest import write_manifest  # numpy/stdlib only at import time

    width, height = int(clip.size[0]), int(clip.size[1])
    if width <= 0 or height <= 0:
        raise InputError(f"movie clip '{clip.name}' has no frames", clip.filepath, "load footage into the clip")
    video, frames = clip_frames(clip)
    fs = int(clip.frame_start)
    n = int(clip.frame_duration)
    if frames is not None:
        n = min(n, len(frames)) if n > 0 else len(frames)
        frames = frames[:n]
    fe = fs + n - 1
    fps = float(getattr(clip, "fps", 0) or scene.render.fps / scene.render.fps_base)
    cams = None
    cam_obj = cam_obj or scene.camera
    if with_cameras and cam_obj is not None:
        r = scene.render
        keep = (r.resolution_x, r.resolution_y, r.resolution_percentage)
        try:
            r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
            cams = [{"frame": int(c["frame"]), "K": c["K"], "w2c": c["w2c"], "dist": None}
                    for c in sample_camera(scene, cam_obj, range(fs, fe + 1))]
        finally:
            r.resolution_x, r.resolution_y, r.resolution_percentage = keep
    return write_manifest(path, width=width, height=height, fps=fps, frame_start=fs, frame_end=fe,
                          video=video, frames=frames, cameras=cams)


def edited_nodes(collection) -> bundle_io.NodeArrays:
    """The bundle's nodes with the splines read back from the collection's Empties."""
    bdir = Path(collection["ms_bundle"])
    b = bundle_io.load_bundle(bdir)
    if b.nodes is None:
        raise InputError("the bundle has no nodes.npz", bdir, "re-run the engine")
    empties = build.node_empties(collection)
    if len(empties) != b.nodes.count:
        raise InputError(f"{len(empties)} node Empties in '{collection.name}' but {b.nodes.count} nodes in the "
                         "bundle", bdir / bundle_io.NODES_FILE, "re-import the bundle")
    d = fcurves.read_node_fcurves(empties, resample=True)
    tm = b.scene["time"]
    fs, fe = tm["frame_start"], tm["frame_end"]
    kt, pos_out = fcurves.frames_to_engine_keys(d["key_frames"], d["loc_tangents_out"], fs, fe)
    _, pos_in = fcurves.frames_to_engine_keys(d["key_frames"], d["loc_tangents_in"], fs, fe)
    _, rot_out = fcurves.frames_to_engine_keys(d["key_frames"], d["rot_tangents_out"], fs, fe)
    _, rot_in = fcurves.frames_to_engine_keys(d["key_frames"], d["rot_tangents_in"], fs, fe)
    arrays = b.nodes.to_dict()
    arrays.update(key_times=kt, pos_keys=d["loc_keys"], pos_tangents=pos_out, rot_keys=d["rot_keys"],
                  rot_tangents=rot_out)
    broken = not (np.allclose(pos_in, pos_out, atol=1e-6) and np.allclose(rot_in, rot_out, atol=1e-6))
    arrays.pop("pos_tangents_in", None)
    arrays.pop("rot_tangents_in", None)
    if broken:
        arrays.update(pos_tangents_in=pos_in, rot_tangents_in=rot_in)
    arrays = {k: (np.asarray(v, np.float32) if k not in ("bind_idx", "graph_idx") else v) for k, v in arrays.items()}
    return bundle_io.NodeArrays.from_dict(arrays, bdir / bundle_io.NODES_FILE)


def send_edits(collection) -> Path:
    """Write the Empties' edited splines into the bundle's ``nodes.npz`` (atomic)."""
    nodes = edited_nodes(collection)
    path = Path(collection["ms_bundle"]) / bundle_io.NODES_FILE
    bundle_io.write_nodes(path, nodes)
    return path


def export_ply(collection, path) -> int:
    """Write the bundle's canonical Gaussians as a standard 3DGS PLY; returns the count."""
    b = bundle_io.load_bundle(collection["ms_bundle"])
    if b.gaussians is None:
        raise InputError("the bundle has no gaussians.ply yet", b.path, "train the bundle first")
    bundle_io.write_ply(os.fspath(path), b.gaussians)
    return b.gaussians.count
