# SPDX-License-Identifier: GPL-3.0-or-later
"""The live preview rig: an Armature that follows the node Empties and skins the
Gaussian mesh with dual quaternions.

Bone ``i`` rests at the node's canonical centre ``c_i`` with identity orientation and
copies the world transform of Empty ``i`` (location ``p_i(t)``, rotation ``q_i(t)``), so
its deform matrix is ``[R(q_i) | p_i − R(q_i) c_i]`` — exactly the engine's node
transform. The Gaussian mesh carries one vertex group per bone with the engine's RBF
binding weights, and an Armature modifier with *Preserve Volume* (Blender's
dual-quaternion skinning) blends them like the engine's DQB.

Sign alignment: Blender flips each bone's quaternion against the running weighted sum
(in the vertex's deform-weight order), the engine against the heaviest neighbour. The
weights are stored column by column of ``bind_idx`` (nearest node first, which is the
heaviest for RBF weights), so both start from the same node and agree whenever a
Gaussian's nodes are rotated less than ~180° relative to each other, i.e. in practice.

Limits: keep the armature and mesh objects at the identity transform (bones copy the
Empties in world space), and the Empties at unit scale — Blender's DQS would apply an
Empty's scale, the engine's node transform has none.
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


def _collection_of(context_or_collection):
    if isinstance(context_or_collection, bpy.types.Collection):
        return context_or_collection
    ctx = context_or_collection if context_or_collection is not None else bpy.context
    return getattr(ctx, "collection", None) or ctx.scene.collection


def build_rig(context_or_collection, empties, centers, mesh_points, bind_idx, bind_w,
              name: str = "MotionSplatsRig", radii=None, mesh_name: str | None = None):
    """Build the armature and a skinned mesh of the canonical points.

    Parameters
    ----------
    context_or_collection : ``bpy.types.Collection`` to link into, or a context (its
        active collection, else the scene collection). Must be in the active view layer.
    empties : N node Empties (animated in world space, unparented).
    centers : (N, 3) canonical node centres.
    mesh_points : (G, 3) canonical Gaussian centres (vertex ``g`` = Gaussian ``g``).
    bind_idx, bind_w : (G, K) node indices and weights per vertex.
    radii : optional (N,) node radii, only for the displayed bone length.

    Returns
    -------
    ``(armature_obj, mesh_obj)``; the mesh has one vertex group per bone and an
    Armature modifier with Preserve Volume (dual-quaternion skinning).
    """
    collection = _collection_of(context_or_collection)
    mesh_obj = build_points_mesh(mesh_name or f"{name}Mesh", mesh_points, collection)
    arm_obj = _build_armature(collection, empties, centers, radii, name)
    assign_vertex_groups(mesh_obj, len(empties), bind_idx, bind_w)
    mod = mesh_obj.modifiers.new("MotionSplatsArmature", "ARMATURE")
    mod.object = arm_obj
    mod.use_deform_preserve_volume = True  # dual-quaternion skinning
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    return arm_obj, mesh_obj


def _build_armature(collection, empties, centers, radii, name):
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = len(empties)
    if centers.shape[0] != n:
        raise ValueError(f"{n} empties but {centers.shape[0]} centres")
    if radii is None:  # bone length for display only: a fraction of the node spacing
        extent = float(np.ptp(centers, axis=0).max()) if n > 1 else 1.0
        radii = np.full(n, max(extent, 1e-3) / max(n, 1) ** (1 / 3))
    radii = np.asarray(radii, dtype=np.float64).reshape(n)
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

    return arm_obj


def assign_vertex_groups(mesh_obj, num_nodes: int, bind_idx, bind_w) -> None:
    """One vertex group per node holding the binding weights ``(bind_idx, bind_w) [G, K]``.

    There is no bulk setter for deform weights: ``VertexGroup.add(indices, weight)``
    takes one weight for all its indices (RBF weights are all different) and looks the
    group up in a linked list for every index, which measured 23 s for 2000 nodes and
    200k vertices × 4. Writing the deform layer through BMesh is O(1) per (vertex, node)
    pair: ~0.4 µs, about 0.4 s for 200k × 4 pairs whatever the node count.
    Existing vertex groups and weights of ``mesh_obj`` are replaced.
    """
    import bmesh

    idx = np.asarray(bind_idx, dtype=np.int64)
    w = np.asarray(bind_w, dtype=np.float64)
    mesh = mesh_obj.data
    if idx.shape != w.shape or idx.ndim != 2 or idx.shape[0] != len(mesh.vertices):
        raise ValueError(f"binding shapes {idx.shape}/{w.shape} do not match {len(mesh.vertices)} vertices")
    if idx.size and (idx.min() < 0 or idx.max() >= num_nodes):
        raise ValueError(f"binding indices outside [0, {num_nodes})")
    _reset_vertex_groups(mesh_obj, num_nodes)  # group index i == node i, no weights
    bm = bmesh.new()
    try:
        bm.from_mesh(mesh)
        layer = bm.verts.layers.deform.verify()
        bm.verts.ensure_lookup_table()
        dverts = [v[layer] for v in bm.verts]
        for j in range(idx.shape[1]):  # K columns; the loop body is one dict store per pair
            for dv, node, weight in zip(dverts, idx[:, j].tolist(), w[:, j].tolist()):
                if weight > 0.0:
                    dv[node] = weight
        bm.to_mesh(mesh)
    finally:
        bm.free()
    mesh.update()


def _reset_vertex_groups(mesh_obj, num_nodes: int) -> None:
    """Groups ``node_00000 ..`` at indices ``0 .. num_nodes-1`` and no weights.

    Existing groups are reused (``vertex_groups.clear()`` costs seconds on big meshes:
    it visits every vertex once per group).
    """
    groups = mesh_obj.vertex_groups
    if len(groups):
        _drop_deform_layer(mesh_obj.data)
        while len(groups) > num_nodes:  # rare: the rig shrank
            groups.remove(groups[len(groups) - 1])
        names = [bone_name(i) for i in range(len(groups))]
        if [g.name for g in groups] != names:
            for i, g in enumerate(groups):  # via unique temporaries: no '.001' clashes
                g.name = f"__ms_tmp_{i}"
            for g, name in zip(groups, names):
                g.name = name
    for i in range(len(groups), num_nodes):
        groups.new(name=bone_name(i))


def _drop_deform_layer(mesh) -> None:
    import bmesh

    bm = bmesh.new()
    try:
        bm.from_mesh(mesh)
        layer = bm.verts.layers.deform.active
        if layer is not None:
            bm.verts.layers.deform.remove(layer)
        bm.to_mesh(mesh)
    finally:
        bm.free()


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
