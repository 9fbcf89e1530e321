# SPDX-License-Identifier: GPL-3.0-or-later
"""Scene -> engine files: camera paths, clip manifests, edited node splines.

Every writer is atomic (temp file + ``os.replace``) and validates before it writes.
"""

from __future__ import annotations

import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from . import build, fcurves
from ..engine import bundle as bundle_io
from ..engine.errors import InputError
from ..engine.fsutil import atomic_write_json
from ..engine.geometry.blender_camera import blender_camera_intrinsics, w2c_from_blender_matrix

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
            w2c = w2c_from_blender_matrix(np.array(cam_obj.matrix_world))
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


def clip_range(clip) -> tuple[str | None, list[str] | None, int, int]:
    """``(video, frames, frame_start, frame_end)`` of a Movie Clip (scene frames)."""
    width, height = int(clip.size[0]), int(clip.size[1])
    if width <= 0 or height <= 0:
        raise InputError(f"movie clip '{clip.name}' has no frames", clip.filepath, "load footage into the clip")
    video, frames = clip_frames(clip)
    fs = int(clip.frame_start)
    n = int(clip.frame_duration)
    if frames is not None:
        n = min(n, len(frames)) if n > 0 else len(frames)
        frames = frames[:n]
    return video, frames, fs, fs + n - 1


def clip_cameras(scene, clip, cam_obj) -> list[dict]:
    """``cam_obj`` sampled on the clip's frames at the clip's size (the render settings are
    restored): ``[{"frame", "K", "w2c", "dist"}]``."""
    fs, fe = clip_range(clip)[2:]
    r = scene.render
    keep = (r.resolution_x, r.resolution_y, r.resolution_percentage)
    try:
        r.resolution_x, r.resolution_y, r.resolution_percentage = int(clip.size[0]), int(clip.size[1]), 100
        return [{"frame": int(c["frame"]), "K": c["K"], "w2c": c["w2c"], "dist": None}
                for c in sample_camera(scene, cam_obj, range(fs, fe + 1))]
    finally:
        r.resolution_x, r.resolution_y, r.resolution_percentage = keep


def write_clip_manifest(path, scene, clip, cam_obj=None, with_cameras: bool = True, cameras=None) -> dict:
    """Clip manifest (``docs/clip_manifest.md``) for Movie Clip ``clip`` and the scene camera.

    The clip's frames are the scene frames ``clip.frame_start ..`` (its duration); the
    cameras are ``cameras`` (from :func:`clip_cameras`) or, when None and
    ``with_cameras``, ``cam_obj`` (default the scene camera) sampled on those frames.
    """
    from ..engine.io.manifest import write_manifest  # numpy/stdlib only at import time

    video, frames, fs, fe = clip_range(clip)
    fps = float(getattr(clip, "fps", 0) or scene.render.fps / scene.render.fps_base)
    cam_obj = cam_obj or scene.camera
    if cameras is None and with_cameras and cam_obj is not None:
        cameras = clip_cameras(scene, clip, cam_obj)
    return write_manifest(path, width=int(clip.size[0]), height=int(clip.size[1]), fps=fps, frame_start=fs,
                          frame_end=fe, video=video, frames=frames, cameras=cameras or None)


#: A read-back key differs from the bundle by more than this (relative to the node's
#: largest key) only when an artist changed it: F-curves hold float32 values, and handle
#: slopes add ~1e-7 relative noise.
EDIT_TOL = 1e-5


@dataclass
class SentEdits:
    """What :func:`send_edits` did."""

    path: Path | None  # nodes.npz written (None: nothing was edited, nothing written)
    backup: Path | None  # copy of the previous nodes.npz
    edited: list  # indices of the nodes whose splines changed
    rekeyed: bool  # the shared knot times changed (a key added or removed at a frame no node had / has left)


def _node_changed(keys, out, inn, ref_keys, ref_out, ref_in) -> np.ndarray:
    """``[N]`` bool: the read-back spline of a node differs from the bundle's.

    All arrays ``[N, K, C]`` in per-frame units; tangents are compared in value units per
    key spacing of one frame, so they weigh like the keys.
    """
    scale = 1.0 + np.abs(ref_keys).max(axis=(1, 2))
    diff = np.maximum.reduce([np.abs(keys - ref_keys).max(axis=(1, 2)), np.abs(out - ref_out).max(axis=(1, 2)),
                              np.abs(inn - ref_in).max(axis=(1, 2))])
    return diff > EDIT_TOL * scale


#: Frames closer than this are the same knot (F-curve key frames are float32).
FRAME_TOL = 1e-4


def edited_nodes(collection) -> tuple[bundle_io.NodeArrays, list, bool]:
    """The bundle's nodes with the edited splines read back from the collection's Empties.

    Returns ``(nodes, edited, rekeyed)``. The knots of the result are the union of the
    Empties' key frames (``nodes.npz`` has one ``key_times`` for all nodes). A node is
    edited when its curve (values or tangents at any knot, beyond float32 noise) or its
    set of keys changed. Unedited nodes keep their arrays bit for bit; where the union
    gained a knot (``rekeyed``: an artist keyed one Empty at a new frame) they get an
    exact split of their Hermite segment there (:mod:`engine.geometry.hermite_knots`), so
    the engine evaluates the same curves, and ``key_mask`` marks it as not their key:
    Blender shows no new key on them. Edited nodes take the read-back keys (their own
    keyframes, the knots they lack split from their own curve) and get separate
    in-tangents only where their handles are really broken.
    """
    from ..engine.geometry.hermite_knots import resample_knots

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
    span = float(fe - fs) or 1.0
    n0 = b.nodes
    frames = d["key_frames"]
    # the union's knots that are the bundle's keep its key times bit for bit
    f0 = fcurves.engine_keys_to_frames(n0.key_times, n0.pos_tangents, fs, fe)[0]
    hi = np.clip(np.searchsorted(f0, frames), 0, len(f0) - 1)
    lo = np.clip(hi - 1, 0, len(f0) - 1)
    near = np.where(np.abs(f0[hi] - frames) <= np.abs(f0[lo] - frames), hi, lo)
    match = np.abs(f0[near] - frames) <= FRAME_TOL
    kt = np.where(match, n0.key_times[near].astype(np.float64), fcurves.frames_to_engine_keys(frames, 0.0, fs, fe)[0])
    rekeyed = not (match.all() and len(frames) == len(f0))
    # the bundle's curves on those knots (engine units): bit for bit where knots are kept
    ref = {}
    for name, inn in (("pos", n0.pos_tangents_in), ("rot", n0.rot_tangents_in)):
        keys, out = getattr(n0, f"{name}_keys"), getattr(n0, f"{name}_tangents")
        inn = out if inn is None else inn
        ref[name] = resample_knots(n0.key_times, kt, keys, out, inn) if rekeyed else (keys, out, inn)
    own0 = np.where(match, n0.own_keys()[:, near], False)  # the bundle's keys on the new knots
    own = d["own"].any(axis=1)  # [N, K]: a frame any channel of the node has a key on
    # read back in engine units; compared in per-frame units (what the Graph Editor shows)
    read = {"pos": (d["loc_keys"], d["loc_tangents_out"] * span, d["loc_tangents_in"] * span),
            "rot": (d["rot_keys"], d["rot_tangents_out"] * span, d["rot_tangents_in"] * span)}
    edited = (own != own0).any(axis=1)  # a key added or removed on the node
    for name in ("pos", "rot"):
        (k1, o1, i1), (k0, o0, i0) = read[name], ref[name]
        edited |= _node_changed(k1, o1 / span, i1 / span, np.asarray(k0, np.float64),
                                        np.asarray(o0, np.float64) / span, np.asarray(i0, np.float64) / span)
    arrays = n0.to_dict()
    arrays.pop("pos_tangents_in", None)
    arrays.pop("rot_tangents_in", None)
    arrays["key_times"] = kt
    e = edited[:, None, None]
    for name in ("pos", "rot"):
        (k1, o1, i1), (k0, o0, i0) = read[name], ref[name]
        keys, out, inn = (np.where(e, a1, a0).astype(np.float32) for a1, a0 in ((k1, k0), (o1, o0), (i1, i0)))
        # handles that read back equal (up to float32 noise) are not broken: one tangent
        same = np.abs(inn - out).max(axis=(1, 2)) <= EDIT_TOL * (1.0 + np.abs(out).max(axis=(1, 2)))
        fresh = edited & same
        inn[fresh] = out[fresh]
        arrays[f"{name}_keys"], arrays[f"{name}_tangents"] = keys, out
        if not np.array_equal(inn, out):
            arrays[f"{name}_tangents_in"] = inn
    mask = np.where(edited[:, None], own, own0)
    arrays["key_mask"] = mask
    if mask.all():
        arrays.pop("key_mask")
    arrays = {k: (np.asarray(v, np.float32) if k not in ("bind_idx", "graph_idx", "key_mask") else v)
              for k, v in arrays.items()}
    nodes = bundle_io.NodeArrays.from_dict(arrays, bdir / bundle_io.NODES_FILE)
    return nodes, [int(i) for i in np.flatnonzero(edited)], bool(rekeyed)


def backup_file(path: Path, kind: str = "edits") -> Path:
    """Copy ``path`` into a new ``<bundle>/backups/<kind>-<time>/`` (as Fine-tune does)."""
    base = path.parent / "backups"
    stamp = time.strftime("%Y%m%d-%H%M%S")
    folder, n = base / f"{kind}-{stamp}", 1
    while folder.exists():
        n += 1
        folder = base / f"{kind}-{stamp}-{n}"
    folder.mkdir(parents=True)
    target = folder / path.name
    shutil.copy2(path, target)
    return target


def send_edits(collection) -> SentEdits:
    """Write the Empties' edited splines into the bundle's ``nodes.npz`` (atomic), after
    backing the old file up into ``<bundle>/backups/edits-<time>/``; nothing is written
    when no node was edited."""
    nodes, edited, rekeyed = edited_nodes(collection)
    path = Path(collection["ms_bundle"]) / bundle_io.NODES_FILE
    if not edited:
        return SentEdits(None, None, [], False)
    backup = backup_file(path)
    bundle_io.write_nodes(path, nodes)
    return SentEdits(path, backup, edited, rekeyed)


def export_ply(collection, path) -> int:
    """Write the bundle's canonical Gaussians as a standard 3DGS PLY; returns the count."""
    b = bundle_io.load_bundle(collection["ms_bundle"])
    if b.gaussians is None:
        raise InputError("the bundle has no gaussians.ply yet", b.path, "train the bundle first")
    bundle_io.write_ply(os.fspath(path), b.gaussians)
    return b.gaussians.count
