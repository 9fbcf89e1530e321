# SPDX-License-Identifier: GPL-3.0-or-later
"""The live preview rig: an Armature that follows the node Empties and skins the
Gaussian mesh with dual quaternions.

Bone ``i`` rests at the node's canonical centre ``c_i`` with identity orientation and
copies the world transform of Empty ``i`` (location ``p_i(t)``, rotation ``q_i(t)``), so
its deform matrix is ``[R(q_i) | p_i − R(q_i) c_i]`` — exactly the engine's node
transform. The Gaussian mesh carries one vertex group per bone with the engine's RBF
binding weights, and an Armature modifier with *Preserve Volume* (Blender's
dual-quaternion skinning) blends them like the engine's DQB. (Blender aligns quaternion
signs to the running sum, the engine to the heaviest node; the two agree whenever a
Gaussian's nodes are rotated less than 180° relative to each other, i.e. in practice.)
"""

from __future__ import annotations

import bpy
import numpy as np

BONE_LENGTH_FRACTION = 0.5  # of the node radius; purely visual


def bone_name(i: int) -> str:
    return f"node_{i:05d}"


def build_points_mesh(name: str, points, collection) -> bpy.types.Object:
    """A mesh object with one vertex per point (``points [G, 3]``), via foreach_set."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(points))
    mesh.vertices.foreach_set("co", points.ravel())
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def build_rig(collection, empties, centers, radii, mesh_obj, bind_idx, bind_w, name: str = "MotionSplatsRig"):
    """Build the armature and skin ``mesh_obj`` to it.

    Parameters
    ----------
    collection : bpy.types.Collection to link the armature into.
    empties : N node Empties (animated in world space, unparented).
    centers : (N, 3) canonical node centres; radii : (N,).
    mesh_obj : mesh object whose vertex ``g`` is canonical Gaussian ``g``.
    bind_idx, bind_w : (G, K) node indices and weights per vertex.

    Returns
    -------
    The armature object (the mesh gets an Armature modifier with Preserve Volume).
    """
    centers = np.asarray(centers, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    n = len(empties)
    arm_data = bpy.data.armatures.new(name)
    arm_obj = bpy.data.objects.new(name, arm_data)
    collection.objects.link(arm_obj)
    arm_data.display_type = "STICK"
    arm_obj.show_in_front = True

    view_layer = bpy.context.view_layer
    view_layer.update()
    if view_layer.objects.get(arm_obj.name) is None:
        raise RuntimeError(f"collection '{collection.name}' is not in the active view layer")
    previous_active = view_layer.objects.active
    view_layer.objects.active = arm_obj
    bpy.ops.object.mode_set(mode="EDIT")
    try:
        bones = arm_data.edit_bones
        lengths = np.maximum(radii * BONE_LENGTH_FRACTION, 1e-4)
        for i in range(n):  # edit bones can only be created one by one
            b = bones.new(bone_name(i))
            b.head = centers[i]
            b.tail = centers[i] + np.array([0.0, lengths[i], 0.0])  # +Y, roll 0: identity rest
            b.roll = 0.0
            b.use_deform = True
    finally:
        bpy.ops.object.mode_set(mode="OBJECT")
        view_layer.objects.active = previous_active

    for i, empty in enumerate(empties):
        con = arm_obj.pose.bones[bone_name(i)].constraints.new("COPY_TRANSFORMS")
        con.target = empty
        con.target_space = "WORLD"
        con.owner_space = "WORLD"

    assign_vertex_groups(mesh_obj, n, bind_idx, bind_w)
    mod = mesh_obj.modifiers.new("MotionSplatsArmature", "ARMATURE")
    mod.object = arm_obj
    mod.use_deform_preserve_volume = True  # dual-quaternion skinning
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    return arm_obj


def assign_vertex_groups(mesh_obj, num_nodes: int, bind_idx, bind_w) -> None:
    """One vertex group per node holding the binding weights ``(bind_idx, bind_w) [G, K]``.

    ``VertexGroup.add`` takes one weight per call, so pairs are added one by one; this
    costs ~1 µs per (vertex, node) pair (0.8 s for 200k Gaussians × 4 nodes).
    """
    idx = np.asarray(bind_idx, dtype=np.int64)
    w = np.asarray(bind_w, dtype=np.float64)
    groups = [mesh_obj.vertex_groups.new(name=bone_name(i)) for i in range(num_nodes)]
    verts = np.repeat(np.arange(idx.shape[0]), idx.shape[1])
    order = np.argsort(idx.ravel(), kind="stable")
    nodes_sorted = idx.ravel()[order]
    verts_sorted = verts[order].tolist()
    w_sorted = w.ravel()[order].tolist()
    bounds = np.searchsorted(nodes_sorted, np.arange(num_nodes + 1)).tolist()
    for node in range(num_nodes):
        add = groups[node].add
        for j in range(bounds[node], bounds[node + 1]):
            add((verts_sorted[j],), w_sorted[j], "REPLACE")


def evaluated_vertex_positions(obj, depsgraph=None) -> np.ndarray:
    """World-space vertex positions ``[G, 3]`` of ``obj`` after modifiers."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    mesh = ev.to_mesh()
    try:
        co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    co = co.reshape(-1, 3).astype(np.float64)
    m = np.array(obj.matrix_world)
    return co @ m[:3, :3].T + m[:3, 3]
