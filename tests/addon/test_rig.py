"""The armature rig reproduces the engine's dual-quaternion blending."""

import numpy as np
import torch

import bpy
from engine.geometry.binding import bind_gaussians
from engine.geometry.dualquat import deform_points
from engine.geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_eval_quat
from engine.geometry.quaternion import quat_from_axis_angle


def test_rig_matches_engine_dqb(extension, empty_scene, tmp_path):
    fcurves, rig = extension.addon.fcurves, extension.addon.rig
    g = torch.Generator().manual_seed(0)
    n, verts, k = 220, 20000, 5
    scale = 2.0  # scene extent
    centers = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * scale
    radii = torch.full((n,), 0.35, dtype=torch.float64)
    points = centers[torch.randint(0, n, (verts,), generator=g)] + 0.2 * torch.randn(verts, 3, generator=g,
                                                                                      dtype=torch.float64)
    idx, w = bind_gaussians(points, centers, radii, 4)
    kt = torch.linspace(0, 1, k, dtype=torch.float64)
    pos = centers[:, None] + 0.3 * torch.randn(n, k, 3, generator=g, dtype=torch.float64)
    axis = torch.randn(n, k, 3, generator=g, dtype=torch.float64)
    # up to ±1.5 rad per node: neighbours then differ by < 180°, where Blender's sign
    # alignment (to the running sum) and the engine's (to the heaviest node) agree
    ang = (0.6 * torch.randn(n, k, generator=g, dtype=torch.float64)).clamp(-1.5, 1.5)
    rot = quat_from_axis_angle(axis, ang)
    rot = torch.where((rot[..., :1] < 0), -rot, rot)
    pos_t, rot_t = catmull_rom_tangents(kt, pos), catmull_rom_tangents(kt, rot)

    scene = empty_scene
    scene.frame_start, scene.frame_end = 1, 25
    col = bpy.data.collections.new("MotionSplats")
    scene.collection.children.link(col)
    empties = []
    for i in range(n):
        e = bpy.data.objects.new(f"node_{i}", None)
        col.objects.link(e)
        empties.append(e)
    frames, pos_tf = fcurves.engine_keys_to_frames(kt.numpy(), pos_t.numpy(), 1, 25)
    _, rot_tf = fcurves.engine_keys_to_frames(kt.numpy(), rot_t.numpy(), 1, 25)
    fcurves.write_node_fcurves(empties, frames, pos.numpy(), pos_tf, rot.numpy(), rot_tf)
    arm, mesh = rig.build_rig(col, empties, centers.numpy(), points.numpy(), idx.numpy(), w.numpy(),
                              radii=radii.numpy(), mesh_name="Gaussians")
    assert mesh.name == "Gaussians" and len(mesh.data.vertices) == verts and len(arm.data.bones) == n
    assert mesh.modifiers[0].use_deform_preserve_volume

    def check():
        for f in (1, 6, 13.5, 25):
            scene.frame_set(int(f), subframe=f - int(f))
            got = rig.evaluated_vertex_positions(bpy.data.objects["Gaussians"])
            t = torch.tensor([(f - 1) / 24], dtype=torch.float64)
            p = hermite_eval(kt, pos, pos_t, t)[:, 0]
            q = hermite_eval_quat(kt, rot, rot_t, t)[:, 0]
            ref = deform_points(centers, p, q, idx, w, points).numpy()
            err = np.abs(got - ref).max()
            assert err <= 1e-4 * scale, (f, err)

    check()
    path = str(tmp_path / "rig.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    scene = bpy.context.scene
    check()


def test_build_rig_accepts_context(extension, empty_scene):
    """A context works too (scene collection) and the default bone length is finite."""
    rig = extension.addon.rig
    e = bpy.data.objects.new("n0", None)
    bpy.context.scene.collection.objects.link(e)
    arm, mesh = rig.build_rig(bpy.context, [e], np.zeros((1, 3)), np.ones((3, 3)),
                              np.zeros((3, 1), np.int64), np.ones((3, 1)))
    assert arm.name in bpy.context.scene.collection.objects and mesh.name in bpy.context.scene.collection.objects
    assert [g.name for g in mesh.vertex_groups] == [b.name for b in arm.data.bones]
