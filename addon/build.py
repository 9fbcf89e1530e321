# SPDX-License-Identifier: GPL-3.0-or-later
"""Build a result bundle into the Blender scene.

``build_bundle_into_scene`` creates, in a new collection:

* one Empty per node with location / quaternion F-curves (the engine's Hermite splines,
  exactly, via :mod:`.fcurves`), keyed on the bundle's time map;
* the preview rig (:func:`.rig.build_rig`): an Armature copying the Empties and a mesh
  with one vertex per kept Gaussian, skinned with dual quaternions;
* point attributes on that mesh (``ms_color`` FLOAT_COLOR from the SH DC term,
  ``ms_opacity`` FLOAT, ``ms_scale`` FLOAT_VECTOR linear σ, ``ms_rot`` QUATERNION wxyz,
  ``ms_index`` INT original Gaussian index, ``ms_center`` BOOLEAN, ``ms_aux`` INT);
* a Geometry Nodes modifier after the Armature modifier. It makes a fresh point cloud
  (Points node + Sample Index of the deformed positions and ``ms_*`` attributes; Mesh to
  Points would copy the rig's N vertex groups onto every point, ~10 s/frame at 2000
  nodes): ``POINTS`` (radius = mean σ × "Radius Scale") or ``ELLIPSOIDS`` for Cycles
  (Instance on Points of an 80-face ico-sphere enclosing 3σ, scaled by σ per axis);
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
from ..engine import bundle as bundle_io
from ..engine.geometry.blender_camera import quat_to_matrix_np as quat_to_matrix

PREVIEW_MODES = ("POINTS", "ELLIPSOIDS")
GN_MODIFIER = "MotionSplatsPreview"
GN_TREE = {"POINTS": "MotionSplatsPoints", "ELLIPSOIDS": "MotionSplatsEllipsoids"}
SEED = 0  # density subsets are deterministic
AUX_AXES = 2  # auxiliary vertices per Gaussian in ELLIPSOIDS builds (local x and y axes)


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


def set_gaussian_attributes(mesh, gaussians, keep, aux: bool) -> None:
    """Point attributes of the kept Gaussians (repeated on their aux vertices)."""
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
    if aux:
        arrays = [np.concatenate([a, np.repeat(a, AUX_AXES, axis=0)]) for a in arrays]
        arrays[5][g:] = False
        arrays[6][g:] = 0
    colors, opac, scales, q, idx, center, aux_idx = arrays
    _set_attr(mesh, "ms_color", "FLOAT_COLOR", colors, "color")
    _set_attr(mesh, "ms_opacity", "FLOAT", opac)
    _set_attr(mesh, "ms_scale", "FLOAT_VECTOR", scales, "vector")
    _set_attr(mesh, "ms_rot", "QUATERNION", q)
    _set_attr(mesh, "ms_index", "INT", idx)
    _set_attr(mesh, "ms_center", "BOOLEAN", center)
    _set_attr(mesh, "ms_aux", "INT", aux_idx)
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
    """Write the node splines of ``nodes`` on ``empties``; returns the key frames."""
    tm = scene_desc["time"]
    fs, fe = tm["frame_start"], tm["frame_end"]
    frames, pos_t = fcurves.engine_keys_to_frames(nodes.key_times, nodes.pos_tangents, fs, fe)
    _, rot_t = fcurves.engine_keys_to_frames(nodes.key_times, nodes.rot_tangents, fs, fe)
    pos_in = rot_in = None
    if nodes.pos_tangents_in is not None:
        pos_in = fcurves.engine_keys_to_frames(nodes.key_times, nodes.pos_tangents_in, fs, fe)[1]
    if nodes.rot_tangents_in is not None:
        rot_in = fcurves.engine_keys_to_frames(nodes.key_times, nodes.rot_tangents_in, fs, fe)[1]
    fcurves.write_node_fcurves(empties, frames, nodes.pos_keys, pos_t, nodes.rot_keys, rot_t, pos_in, rot_in)
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
    set_gaussian_attributes(mesh_obj.data, gs, keep, aux)
    mesh_obj["ms_gaussians"] = len(keep)
    timings["attributes"] = _time.perf_counter() - t
    t = _time.perf_counter()
    add_preview_modifier(mesh_obj, preview)
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
# Geometry Nodes previews and materials
# ----------------------------------------------------------------------------------
def _socket(sockets, name: str, index: int = 0):
    """The ``index``-th enabled socket called ``name`` (dynamic nodes hide unused ones)."""
    found = [s for s in sockets if s.name == name and getattr(s, "enabled", True)]
    return found[index]


def _named_attr(nodes, name: str, dtype: str):
    n = nodes.new("GeometryNodeInputNamedAttribute")
    n.data_type = dtype
    n.inputs["Name"].default_value = name
    return _socket(n.outputs, "Attribute")


class _Tree:
    """Small builder for the preview node groups."""

    def __init__(self, name: str, inputs=()):
        self.tree = tree = bpy.data.node_groups.new(name, "GeometryNodeTree")
        tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        for sock_name, default in inputs:
            s = tree.interface.new_socket(sock_name, in_out="INPUT", socket_type="NodeSocketFloat")
            s.default_value, s.min_value = default, 0.0
        tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        self.N, self.L = tree.nodes, tree.links
        self.gin, self.gout = self.N.new("NodeGroupInput"), self.N.new("NodeGroupOutput")
        self.index = self.N.new("GeometryNodeInputIndex").outputs["Index"]
        self.position = self.N.new("GeometryNodeInputPosition").outputs["Position"]

    def node(self, idname, **props):
        n = self.N.new(idname)
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def link(self, a, b):
        if isinstance(a, (int, float, tuple)):
            b.default_value = a
        else:
            self.L.new(a, b)

    def math(self, op, a, b, kind="ShaderNodeMath"):
        n = self.node(kind, operation=op)
        self.link(a, n.inputs[0])
        self.link(b, n.inputs[1])
        scalar = kind == "ShaderNodeMath" or op in ("DOT_PRODUCT", "LENGTH", "DISTANCE")
        return n.outputs["Value"] if scalar else n.outputs["Vector"]

    def sample(self, geo, value, dtype, index):
        """``value`` (a field on the Gaussian mesh) read at ``index`` of the consuming context."""
        n = self.node("GeometryNodeSampleIndex", data_type=dtype, domain="POINT")
        self.link(geo, n.inputs["Geometry"])
        self.link(value, _socket(n.inputs, "Value"))
        self.link(index, n.inputs["Index"])
        return _socket(n.outputs, "Value")

    def store(self, geo, name, dtype, value):
        n = self.node("GeometryNodeStoreNamedAttribute", data_type=dtype, domain="POINT")
        self.link(geo, n.inputs["Geometry"])
        n.inputs["Name"].default_value = name
        self.link(value, _socket(n.inputs, "Value"))
        return n.outputs["Geometry"]

    def splat_points(self, aux_per_gaussian: int):
        """A new point cloud with one point per Gaussian at its (deformed) position,
        carrying ``ms_color``/``ms_opacity``, plus the sampled ``ms_scale`` field.

        The points are made with the Points node and Sample Index instead of Mesh to
        Points: the rig's ~N vertex groups would otherwise be copied onto every point
        (or have to be removed, which costs seconds per frame with 2000 groups).
        """
        geo = self.gin.outputs["Geometry"]
        size = self.node("GeometryNodeAttributeDomainSize", component="MESH")
        self.link(geo, size.inputs["Geometry"])
        count = self.math("DIVIDE", size.outputs["Point Count"], float(1 + aux_per_gaussian))
        pts = self.node("GeometryNodePoints")
        self.link(count, pts.inputs["Count"])
        self.link(self.sample(geo, self.position, "FLOAT_VECTOR", self.index), pts.inputs["Position"])
        scale = self.sample(geo, _named_attr(self.N, "ms_scale", "FLOAT_VECTOR"), "FLOAT_VECTOR", self.index)
        out = pts.outputs["Points"]
        out = self.store(out, "ms_color", "FLOAT_COLOR",
                         self.sample(geo, _named_attr(self.N, "ms_color", "FLOAT_COLOR"), "FLOAT_COLOR", self.index))
        out = self.store(out, "ms_opacity", "FLOAT",
                         self.sample(geo, _named_attr(self.N, "ms_opacity", "FLOAT"), "FLOAT", self.index))
        return geo, pts, out, scale, count

    def finish(self, geo, material):
        setmat = self.node("GeometryNodeSetMaterial")
        setmat.inputs["Material"].default_value = material
        self.link(geo, setmat.inputs["Geometry"])
        self.link(setmat.outputs["Geometry"], self.gout.inputs["Geometry"])
        return self.tree


def _points_tree(material):
    t = _Tree(GN_TREE["POINTS"], inputs=(("Radius Scale", 1.0),))
    _, pts, out, scale, _ = t.splat_points(0)
    mean = t.math("DOT_PRODUCT", scale, (1 / 3, 1 / 3, 1 / 3), kind="ShaderNodeVectorMath")
    t.link(t.math("MULTIPLY", mean, t.gin.outputs["Radius Scale"]), pts.inputs["Radius"])
    return t.finish(out, material)


#: Ico-sphere radius in σ units: subdivision 2 (80 faces) has an inradius of ~0.94 of its
#: circumradius, so 3.3 encloses the 3σ sphere the shader cuts the Gaussian at.
ICO_RADIUS, ICO_SUBDIVISIONS, CUTOFF_SIGMA = 3.3, 2, 3.0


def _ellipsoid_tree(material, subdivisions: int = ICO_SUBDIVISIONS):
    t = _Tree(GN_TREE["ELLIPSOIDS"])
    geo, _, out, scale, count = t.splat_points(AUX_AXES)
    axes = []
    first_aux = t.math("ADD", count, t.math("MULTIPLY", t.index, float(AUX_AXES)))  # G + AUX·i
    for k in range(AUX_AXES):  # the deformed local x and y axes define the rotation
        aux = t.sample(geo, t.position, "FLOAT_VECTOR", t.math("ADD", first_aux, float(k)))
        axes.append(t.math("SUBTRACT", aux, t.position, kind="ShaderNodeVectorMath"))
    a2r = t.node("FunctionNodeAxesToRotation", primary_axis="X", secondary_axis="Y")
    t.link(axes[0], a2r.inputs["Primary Axis"])
    t.link(axes[1], a2r.inputs["Secondary Axis"])
    ico = t.node("GeometryNodeMeshIcoSphere")
    ico.inputs["Radius"].default_value = ICO_RADIUS  # instance space is in σ units
    ico.inputs["Subdivisions"].default_value = subdivisions
    iop = t.node("GeometryNodeInstanceOnPoints")
    t.link(out, iop.inputs["Points"])
    t.link(ico.outputs["Mesh"], iop.inputs["Instance"])
    t.link(a2r.outputs["Rotation"], iop.inputs["Rotation"])
    t.link(scale, iop.inputs["Scale"])
    return t.finish(iop.outputs["Instances"], material)


def _material(name: str, ellipsoid: bool):
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0) and not mat.use_nodes:  # always node-based from 5.0
        mat.use_nodes = True
    if hasattr(mat, "surface_render_method"):
        mat.surface_render_method = "DITHERED"
    nt = mat.node_tree
    N, L = nt.nodes, nt.links
    N.clear()
    kind = "INSTANCER" if ellipsoid else "GEOMETRY"
    col = N.new("ShaderNodeAttribute")
    col.attribute_type, col.attribute_name = kind, "ms_color"
    op = N.new("ShaderNodeAttribute")
    op.attribute_type, op.attribute_name = kind, "ms_opacity"
    emit = N.new("ShaderNodeEmission")
    L.new(col.outputs["Color"], emit.inputs["Color"])
    emit.inputs["Strength"].default_value = 1.0
    transp = N.new("ShaderNodeBsdfTransparent")
    mix = N.new("ShaderNodeMixShader")
    out = N.new("ShaderNodeOutputMaterial")
    L.new(transp.outputs[0], mix.inputs[1])
    L.new(emit.outputs[0], mix.inputs[2])
    L.new(mix.outputs[0], out.inputs["Surface"])

    def math(op_name, a, b=None, value=None):
        n = N.new("ShaderNodeMath")
        n.operation = op_name
        for i, v in enumerate((a, b)):
            if v is None:
                continue
            if isinstance(v, (int, float)):
                n.inputs[i].default_value = v
            else:
                L.new(v, n.inputs[i])
        return n.outputs[0]

    def vdot(a, b):
        n = N.new("ShaderNodeVectorMath")
        n.operation = "DOT_PRODUCT"
        L.new(a, n.inputs[0])
        L.new(b, n.inputs[1])
        return n.outputs["Value"]

    alpha = op.outputs["Fac"]
    if ellipsoid:
        tc = N.new("ShaderNodeTexCoord")
        geom = N.new("ShaderNodeNewGeometry")
        vt = N.new("ShaderNodeVectorTransform")
        vt.vector_type, vt.convert_from, vt.convert_to = "VECTOR", "WORLD", "OBJECT"
        L.new(geom.outputs["Incoming"], vt.inputs["Vector"])
        p, v = tc.outputs["Object"], vt.outputs["Vector"]
        pp, pv, vv = vdot(p, p), vdot(p, v), vdot(v, v)
        d2 = math("SUBTRACT", pp, math("DIVIDE", math("MULTIPLY", pv, pv), math("MAXIMUM", vv, 1e-12)))
        g = math("EXPONENT", math("MULTIPLY", math("MAXIMUM", d2, 0.0), -0.5))
        alpha = math("MULTIPLY", alpha, g)
        alpha = math("MULTIPLY", alpha, math("LESS_THAN", d2, CUTOFF_SIGMA ** 2))  # 3σ cut
        alpha = math("MULTIPLY", alpha, math("SUBTRACT", 1.0, geom.outputs["Backfacing"]))
    L.new(math("MINIMUM", alpha, 0.99), mix.inputs["Fac"])
    return mat


def add_preview_modifier(mesh_obj, preview: str = "POINTS"):
    """(Re)create the Geometry Nodes preview modifier (after the Armature modifier)."""
    if preview not in PREVIEW_MODES:
        raise ValueError(f"preview must be one of {PREVIEW_MODES}, not {preview!r}")
    old = mesh_obj.modifiers.get(GN_MODIFIER)
    if old is not None:
        mesh_obj.modifiers.remove(old)
    ell = preview == "ELLIPSOIDS"
    mat = _material("MotionSplatsEllipsoid" if ell else "MotionSplatsPoint", ell)
    tree = _ellipsoid_tree(mat) if ell else _points_tree(mat)
    if mat.name not in [m.name for m in mesh_obj.data.materials if m]:
        mesh_obj.data.materials.append(mat)
    mod = mesh_obj.modifiers.new(GN_MODIFIER, "NODES")
    mod.node_group = tree
    mesh_obj["ms_preview"] = preview
    return mod


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
