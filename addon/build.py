# SPDX-License-Identifier: GPL-3.0-or-later
"""Build a result bundle into the Blender scene.

``build_bundle_into_scene`` creates, in a new collection:

* one Empty per node with location / quaternion F-curves (the engine's Hermite splines,
  exactly, via :mod:`.fcurves`), keyed on the bundle's time map;
* the preview rig (:func:`.rig.build_rig`): an Armature copying the Empties and a mesh
  with one vertex per kept Gaussian, skinned with dual quaternions;
* point attributes on that mesh (``ms_color`` FLOAT_COLOR from the SH DC term,
  ``ms_opacity`` FLOAT, ``ms_scale`` FLOAT_VECTOR linear σ, ``ms_rot`` QUATERNION wxyz,
  ``ms_index`` INT original Gaussian index, ``ms_center`` BOOLEAN, ``ms_aux`` INT; and
  ``ms_t_center`` / ``ms_lifespan`` FLOAT, engine time and σ, only for a bundle with
  Gaussian lifespans, :func:`bundle_lifespans`; ``ms_view_origin`` FLOAT_VECTOR / ``ms_view_angle``
  FLOAT, only for a bundle with view-bound Gaussians, :func:`bundle_view_binding`);
* a Geometry Nodes modifier after the Armature modifier. It makes a fresh point cloud
  (Points node + Sample Index of the deformed positions and ``ms_*`` attributes; Mesh to
  Points would copy the rig's N vertex groups onto every point, ~10 s/frame at 2000
  nodes): ``POINTS`` (radius = mean σ × "Radius Scale") or ``ELLIPSOIDS`` for Cycles
  (Instance on Points of an 80-face ico-sphere enclosing 3σ, scaled by σ per axis); with
  lifespans the opacity it passes on follows the frame (:mod:`.preview`, inputs "Frame
  Start" / "Frame End" = the bundle's time range);
* an animated camera for the bundle's cameras (the scene camera only when there is none),
  and the scene frame range / fps. Render settings are :mod:`.render_setup`'s job.

Rotation of the ellipsoids: for every kept Gaussian ``i`` of ``G`` the mesh carries two
auxiliary vertices ``G + 2i + k`` at ``x + h·R(q)·e_k`` (``k`` = the Gaussian's local x
and y axes), bound with the Gaussian's own binding weights. The Armature modifier moves
the three vertices by the same blended rigid transform, so in Geometry Nodes
``Axes to Rotation(aux_x − x, aux_y − x)`` is exactly the deformed Gaussian rotation
``R(dq)·R(q)`` (the engine's ``dq_apply_rotations``). The auxiliary vertices exist only
in ``ELLIPSOIDS`` builds (``ms_center`` is False on them).

Ellipsoid material: alpha is ``opacity · exp(−½ d²)`` where ``d`` is the distance from
the instance centre to the camera ray in instance space (σ units: the instance is scaled
by σ), i.e. the Gaussian's peak along the ray, cut at 3σ; back faces are transparent.
Colour is emitted (Set up render's ``Standard`` view transform shows the DC colour).
"""

from __future__ import annotations

import math
import time as _time
from pathlib import Path

import bpy
import numpy as np

from . import fcurves, rig
from .preview import AUX_AXES, GN_MODIFIER, GN_TREE, PREVIEW_MODES, add_preview_modifier  # noqa: F401
from ..engine import bundle as bundle_io
from ..engine.geometry.blender_camera import quat_to_matrix_np as quat_to_matrix

SEED = 0  # density subsets are deterministic


# ----------------------------------------------------------------------------------
# numpy helpers (no bpy)
# ----------------------------------------------------------------------------------

def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1]."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)

def subset_indices(count: int, density: float) -> np.ndarray:
    """Sorted indices of the Gaussians kept at ``density`` (deterministic, seed 0)."""
    density = float(min(max(density, 0.0), 1.0))
    if density >= 1.0:
        return np.arange(count, dtype=np.int64)
    keep = max(1, int(round(count * density))) if count else 0
    return np.sort(np.random.default_rng(SEED).permutation(count)[:keep]).astype(np.int64)


def aux_points(means, quats, log_scales, extent: float) -> tuple[np.ndarray, np.ndarray]:
    """Auxiliary vertices ``[2G, 3]`` (Gaussian-major; local x then y axis) and offsets ``h [G]``.

    ``h = max(σ_max, 1e-3·extent)`` keeps the axes well conditioned in float32.
    """
    rot = quat_to_matrix(quats)  # [G, 3, 3], columns are the local axes
    h = np.maximum(np.exp(np.asarray(log_scales, np.float64)).max(axis=1), 1e-3 * max(extent, 1e-6))
    pts = np.asarray(means, np.float64)[:, None, :] + h[:, None, None] * rot.transpose(0, 2, 1)[:, :AUX_AXES]
    return pts.reshape(-1, 3), h


# ----------------------------------------------------------------------------------
# scene building
# ----------------------------------------------------------------------------------
def _new_collection(context, name: str):
    col = bpy.data.collections.new(name)
    parent = getattr(context, "collection", None)
    if parent is None or (parent != context.scene.collection and not _in_view_layer(context, parent)):
        parent = context.scene.collection
    parent.children.link(col)
    return col


def _in_view_layer(context, col) -> bool:
    stack = [context.view_layer.layer_collection]
    while stack:
        lc = stack.pop()
        if lc.collection == col:
            return not lc.exclude
        stack.extend(lc.children)
    return False


def _set_attr(mesh, name: str, dtype: str, values, prop: str = "value") -> None:
    attrs = mesh.attributes
    if name in attrs:
        attrs.remove(attrs[name])
    attr = attrs.new(name, dtype, "POINT")
    values = np.ascontiguousarray(values)
    attr.data.foreach_set(prop, values.ravel())


def bundle_lifespans(nodes):
    """``(t_center, lifespan)`` ``(G,)`` float32 of a bundle whose Gaussians have lifespans
    (some ``gauss_lifespan > 0``), else None (every Gaussian always visible)."""
    if nodes is None or nodes.gauss_lifespan is None or not (np.asarray(nodes.gauss_lifespan) > 0).any():
        return None
    return (np.asarray(nodes.gauss_t_center, np.float32), np.asarray(nodes.gauss_lifespan, np.float32))


def bundle_view_binding(nodes):
    """``(origin (G, 3), angle (G,))`` float32 of a bundle with view-bound Gaussians (some
    ``gauss_view_angle > 0``: per-frame detail that fades with the parallax from its own
    camera, :mod:`engine.train.shot_detail`), else None."""
    if nodes is None or nodes.gauss_view_angle is None or not (np.asarray(nodes.gauss_view_angle) > 0).any():
        return None
    return (np.asarray(nodes.gauss_view_origin, np.float32), np.asarray(nodes.gauss_view_angle, np.float32))


def set_gaussian_attributes(mesh, gaussians, keep, aux: bool, lifespans=None, view=None) -> None:
    """Point attributes of the kept Gaussians (repeated on their aux vertices).

    ``lifespans``: :func:`bundle_lifespans` (all Gaussians' rows) or None; with it the mesh
    also gets ``ms_t_center`` and ``ms_lifespan``. ``view``: :func:`bundle_view_binding` or
    None; with it ``ms_view_origin`` and ``ms_view_angle``.
    """
    # The engine's colours are display-referred sRGB values; Blender shades in linear
    # light and applies the sRGB transform on output, so store them linearised.
    colors = np.concatenate([srgb_to_linear(gaussians.colors[keep]), np.ones((len(keep), 1))],
                            axis=1).astype(np.float32)
    opac = gaussians.opacities[keep].astype(np.float32)
    scales = np.exp(gaussians.log_scales[keep]).astype(np.float32)
    q = gaussians.quats[keep].astype(np.float64)
    q = (q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)).astype(np.float32)
    g = len(keep)
    center = np.ones(g, dtype=bool)
    aux_idx = (g + AUX_AXES * np.arange(g)).astype(np.int32) if aux else np.zeros(g, np.int32)
    arrays = [colors, opac, scales, q, keep.astype(np.int32), center, aux_idx]
    n_life = 2 if lifespans is not None else 0
    if lifespans is not None:
        arrays += [np.asarray(a, np.float32)[keep] for a in lifespans]
    if view is not None:
        arrays += [np.asarray(a, np.float32)[keep] for a in view]
    if aux:
        arrays = [np.concatenate([a, np.repeat(a, AUX_AXES, axis=0)]) for a in arrays]
        arrays[5][g:] = False
        arrays[6][g:] = 0
    colors, opac, scales, q, idx, center, aux_idx = arrays[:7]
    _set_attr(mesh, "ms_color", "FLOAT_COLOR", colors, "color")
    _set_attr(mesh, "ms_opacity", "FLOAT", opac)
    _set_attr(mesh, "ms_scale", "FLOAT_VECTOR", scales, "vector")
    _set_attr(mesh, "ms_rot", "QUATERNION", q)
    _set_attr(mesh, "ms_index", "INT", idx)
    _set_attr(mesh, "ms_center", "BOOLEAN", center)
    _set_attr(mesh, "ms_aux", "INT", aux_idx)
    for name, values in zip(("ms_t_center", "ms_lifespan"), arrays[7:7 + n_life]):
        _set_attr(mesh, name, "FLOAT", values)
    if view is not None:
        _set_attr(mesh, "ms_view_origin", "FLOAT_VECTOR", arrays[7 + n_life], "vector")
        _set_attr(mesh, "ms_view_angle", "FLOAT", arrays[8 + n_life])
    mesh.update()


#: A node whose dynamic score ``p_dyn`` reaches this is a moving node.
MOVING_SCORE = 0.5


def _node_groups(collection, nodes) -> tuple:
    """``(moving, static)`` sub-collections of the result (both the result itself when the
    bundle has no dynamic scores)."""
    if nodes.p_dyn is None:
        return collection, collection
    parts = []
    for label, tag in (("moving", "COLOR_01"), ("static", "COLOR_05")):
        sub = bpy.data.collections.new(f"{collection.name}_{label}")
        sub.color_tag = tag  # red / blue in the Outliner
        sub["ms_nodes"] = label
        collection.children.link(sub)
        parts.append(sub)
    return tuple(parts)


def _build_empties(collection, nodes, display: str, name: str):
    """One Empty per node; with dynamic scores, moving nodes (``p_dyn >= MOVING_SCORE``) are
    spheres in a ``moving`` sub-collection and static ones small axes in ``static``."""
    moving_col, static_col = _node_groups(collection, nodes)
    score = np.ones(nodes.count) if nodes.p_dyn is None else np.asarray(nodes.p_dyn, np.float64)
    empties = []
    for i in range(nodes.count):  # objects are created one by one; data goes in bulk
        e = bpy.data.objects.new(f"{name}_{rig.bone_name(i)}", None)
        moving = bool(score[i] >= MOVING_SCORE)
        e.empty_display_type = display if moving or nodes.p_dyn is None else "PLAIN_AXES"
        e.empty_display_size = float(nodes.radii[i]) * (0.5 if e.empty_display_type == "SPHERE" else 0.3)
        e["ms_node"] = i
        e["ms_dynamic"] = float(score[i])
        (moving_col if moving else static_col).objects.link(e)
        empties.append(e)
    return empties


def moving_nodes(collection) -> list:
    """The node Empties of a result whose dynamic score marks them as moving."""
    return [e for e in node_empties(collection) if float(e.get("ms_dynamic", 1.0)) >= MOVING_SCORE]


def write_bundle_fcurves(empties, nodes, scene_desc) -> np.ndarray:
    """Write the node splines of ``nodes`` on ``empties`` (keyframes only on each node's
    own keys, ``nodes.key_mask``); returns the key frames (all knots)."""
    tm = scene_desc["time"]
    fs, fe = tm["frame_start"], tm["frame_end"]
    frames, pos_t = fcurves.engine_keys_to_frames(nodes.key_times, nodes.pos_tangents, fs, fe)
    _, rot_t = fcurves.engine_keys_to_frames(nodes.key_times, nodes.rot_tangents, fs, fe)
    pos_in = rot_in = None
    if nodes.pos_tangents_in is not None:
        pos_in = fcurves.engine_keys_to_frames(nodes.key_times, nodes.pos_tangents_in, fs, fe)[1]
    if nodes.rot_tangents_in is not None:
        rot_in = fcurves.engine_keys_to_frames(nodes.key_times, nodes.rot_tangents_in, fs, fe)[1]
    fcurves.write_node_fcurves(empties, frames, nodes.pos_keys, pos_t, nodes.rot_keys, rot_t, pos_in, rot_in,
                               key_mask=nodes.key_mask)
    return frames


def apply_scene_time(scene, scene_desc) -> None:
    tm = scene_desc["time"]
    scene.frame_start = int(math.floor(tm["frame_start"]))
    scene.frame_end = int(math.ceil(tm["frame_end"]))
    fps = float(tm["fps"])
    scene.render.fps = max(1, int(round(fps)))
    scene.render.fps_base = scene.render.fps / fps


def build_camera(collection, scene, scene_desc, name: str = "MotionSplatsCamera"):
    """An animated camera following ``scene.json`` cameras (None when there are none).

    The one animated-camera builder (:func:`.cameras.build_animated_camera`: linear keys,
    one per camera); it becomes the scene camera only when the scene has none, and the
    render size it needs is stored on it for Set up render.
    """
    from .cameras import build_animated_camera

    cams = scene_desc.get("cameras") or []
    # the training camera path; held-out cameras (another viewpoint at the same times) are
    # for evaluation and would fight over the same keyframes
    cams = [c for c in cams if c.get("split", "train") == "train"] or cams
    if not cams:
        return None
    c0 = cams[0]
    frames = bundle_io.frame_of_time(scene_desc, [c["time"] for c in cams])
    order = np.argsort(frames, kind="stable")
    w2cs = np.stack([np.asarray(cams[j]["w2c"], np.float64) for j in order])
    return build_animated_camera(scene, name, c0["K"], int(c0["width"]), int(c0["height"]), w2cs,
                                 [float(frames[j]) for j in order], collection=collection, set_render=False,
                                 make_scene_camera=scene.camera is None)


def build_bundle_into_scene(context, bundle_dir, collection_name: str | None = None, density: float = 1.0,
                            with_rig: bool = True, preview: str = "POINTS", empty_display: str = "SPHERE",
                            camera: bool = True) -> dict:
    """Load the bundle at ``bundle_dir`` and build it into ``context.scene``.

    Parameters
    ----------
    density : fraction of Gaussians kept (deterministic subset, seed 0).
    with_rig : build the Armature + skinned Gaussian mesh (else a static mesh at the
        canonical positions, with the preview modifier only).
    preview : ``'POINTS'`` or ``'ELLIPSOIDS'``.

    Render settings are left alone (Set up render, :mod:`.render_setup`, is the explicit
    step); only the frame range / rate follow the bundle, and that change is listed in
    ``scene_changes``.

    Returns
    -------
    dict with ``collection``, ``empties`` (list), ``armature``, ``mesh``, ``camera``,
    ``gaussians`` (kept count), ``key_frames``, ``timings`` (seconds per stage) and
    ``scene_changes`` (lines describing changed scene settings).
    """
    if preview not in PREVIEW_MODES:
        raise ValueError(f"preview must be one of {PREVIEW_MODES}, not {preview!r}")
    timings = {}
    t0 = _time.perf_counter()
    b = bundle_io.load_bundle(bundle_dir)
    timings["load"] = _time.perf_counter() - t0
    scene = context.scene
    name = collection_name or f"MotionSplats_{Path(bundle_dir).name}"
    col = _new_collection(context, name)
    col["ms_bundle"] = str(Path(bundle_dir).resolve())
    col["ms_preview"] = preview
    col["ms_density"] = float(density)
    col["ms_time"] = {k: float(b.scene["time"][k]) for k in ("frame_start", "frame_end", "fps")}
    before = (scene.frame_start, scene.frame_end, round(scene.render.fps / scene.render.fps_base, 4))
    apply_scene_time(scene, b.scene)  # the F-curves are keyed on these frames: the timeline must show them
    after = (scene.frame_start, scene.frame_end, round(scene.render.fps / scene.render.fps_base, 4))
    changes = [f"frames, fps: {before} -> {after}"] if before != after else []
    out = {"collection": col, "empties": [], "armature": None, "mesh": None, "camera": None,
           "gaussians": 0, "key_frames": None, "timings": timings, "scene_changes": changes}

    nodes, gs = b.nodes, b.gaussians
    t = _time.perf_counter()
    if nodes is not None:
        empties = _build_empties(col, nodes, empty_display, "MS")
        timings["empties"] = _time.perf_counter() - t
        t = _time.perf_counter()
        out["key_frames"] = write_bundle_fcurves(empties, nodes, b.scene)
        out["empties"] = empties
        timings["fcurves"] = _time.perf_counter() - t

    if gs is not None:
        _build_gaussians(col, name, b, out, density, preview, with_rig)
    t = _time.perf_counter()
    if camera:
        out["camera"] = build_camera(col, scene, b.scene, name=f"{name}_Camera")
    timings["camera"] = _time.perf_counter() - t
    timings["total"] = _time.perf_counter() - t0
    return out


def _build_gaussians(col, name, b, out, density, preview, with_rig) -> None:
    """The (rigged) Gaussian mesh with attributes and preview modifier; fills ``out``."""
    nodes, gs, timings = b.nodes, b.gaussians, out["timings"]
    t = _time.perf_counter()
    keep = subset_indices(gs.count, density)
    means = gs.means[keep].astype(np.float64)
    aux = preview == "ELLIPSOIDS"
    pts = means
    if aux:
        extent = float(np.ptp(means, axis=0).max()) if len(means) else 1.0
        aux_pts, _ = aux_points(means, gs.quats[keep], gs.log_scales[keep], extent)
        pts = np.concatenate([means, aux_pts])
    rigged = with_rig and nodes is not None and nodes.bind_idx is not None and out["empties"]
    if rigged:
        bi, bw = nodes.bind_idx[keep], nodes.bind_w[keep]
        if aux:
            bi = np.concatenate([bi, np.repeat(bi, AUX_AXES, axis=0)])
            bw = np.concatenate([bw, np.repeat(bw, AUX_AXES, axis=0)])
        arm, mesh_obj = rig.build_rig(col, out["empties"], nodes.centers, pts, bi, bw, name=f"{name}Rig",
                                      radii=nodes.radii, mesh_name=f"{name}Gaussians")
        arm["ms_rig"] = True
        out["armature"] = arm
    else:
        mesh_obj = rig.build_points_mesh(f"{name}Gaussians", pts, col)
    timings["rig"] = _time.perf_counter() - t
    t = _time.perf_counter()
    set_gaussian_attributes(mesh_obj.data, gs, keep, aux, bundle_lifespans(nodes), bundle_view_binding(nodes))
    mesh_obj["ms_gaussians"] = len(keep)
    timings["attributes"] = _time.perf_counter() - t
    t = _time.perf_counter()
    tm = b.scene["time"]
    add_preview_modifier(mesh_obj, preview, frame_range=(float(tm["frame_start"]), float(tm["frame_end"])))
    out["mesh"], out["gaussians"] = mesh_obj, len(keep)
    timings["preview"] = _time.perf_counter() - t


def rebuild_preview(context, collection, density: float = 1.0, with_rig: bool = True,
                    preview: str = "POINTS") -> dict:
    """Rebuild only the rig + Gaussian mesh of a built collection.

    The node Empties (and any F-curve edits not yet sent to the bundle) and the camera
    are kept; the armature and Gaussian mesh are replaced.
    """
    if preview not in PREVIEW_MODES:
        raise ValueError(f"preview must be one of {PREVIEW_MODES}, not {preview!r}")
    b = bundle_io.load_bundle(collection["ms_bundle"])
    old = [o for o in collection.objects if "ms_gaussians" in o or "ms_rig" in o]
    datas = [o.data for o in old]
    bpy.data.batch_remove(old)
    bpy.data.batch_remove([d for d in datas if d is not None and d.users == 0])
    out = {"collection": collection, "empties": node_empties(collection), "armature": None, "mesh": None,
           "camera": None, "gaussians": 0, "key_frames": None, "timings": {}}
    if b.gaussians is not None:
        name = collection.name
        _build_gaussians(collection, name, b, out, density, preview, with_rig)
    collection["ms_preview"], collection["ms_density"] = preview, float(density)
    return out


# ----------------------------------------------------------------------------------
# Finding what was built
# ----------------------------------------------------------------------------------
def result_collections() -> list:
    """Every built result collection in the file."""
    return [c for c in bpy.data.collections if "ms_bundle" in c]


def result_of(obj):
    """The result collection ``obj`` belongs to (also through a moving/static sub-collection)."""
    if obj is None:
        return None
    for col in result_collections():
        if obj.name in col.all_objects:
            return col
    return None


def bundle_collection(context):
    """The result to act on: the active object's, else the only one in the file.

    None when there is none, or several and the active object is in none of them (use
    :func:`why_no_result` for the message): acting on "the last one built" would send
    edits to a result the artist did not edit.
    """
    found = result_of(getattr(context, "active_object", None))
    if found is not None:
        return found
    cols = result_collections()
    return cols[0] if len(cols) == 1 else None


def why_no_result(context) -> str:
    """Why :func:`bundle_collection` found nothing, for ``poll_message_set``."""
    n = len(result_collections())
    if n == 0:
        return "No result in the scene: reconstruct or import a bundle first"
    return f"{n} results in the file: select an object of the one to use (a node Empty, its mesh or camera)"


def node_empties(collection) -> list:
    """The node Empties of a built collection, in node order."""
    empties = [o for o in collection.all_objects if o.type == "EMPTY" and "ms_node" in o]
    return sorted(empties, key=lambda o: int(o["ms_node"]))
