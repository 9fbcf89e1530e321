"""Gaussian lifespans in the Blender preview (addon/build.py, addon/preview.py).

A Gaussian with ``gauss_lifespan > 0`` is seen at engine time ``t`` with opacity
``opacity · exp(−½ ((t − gauss_t_center) / gauss_lifespan)²)``; the preview's Geometry
Nodes tree passes that, per frame, to the material as ``ms_opacity``, and leaves out the
Gaussians it puts under the engine's alpha threshold 1/255.
"""

from __future__ import annotations

import numpy as np
import pytest

import bpy

from engine import bundle as bio

FS, FE = 1, 21  # engine time t is frame 1 + 20 t
OPACITY = np.array([0.8, 0.6, 0.7])
T_CENTER = np.array([0.3, 0.5, 0.9], np.float32)  # Gaussian 0 is always visible: its t_center is unused
LIFESPAN = np.array([0.0, 0.05, 0.1], np.float32)  # sigma: 1 and 2 frames


def write_bundle(path, lifespans=True, lifespan=LIFESPAN, cameras=()):
    """Three still Gaussians on one node, Gaussian 0 always visible (lifespan 0)."""
    g = len(OPACITY)
    kt = np.array([0.0, 1.0], np.float32)
    extra = {"gauss_t_center": T_CENTER, "gauss_lifespan": np.asarray(lifespan, np.float32)} if lifespans else {}
    nodes = bio.NodeArrays(centers=np.zeros((1, 3)), radii=np.ones(1), key_times=kt,
                           pos_keys=np.zeros((1, 2, 3)), pos_tangents=np.zeros((1, 2, 3)),
                           rot_keys=np.tile([1.0, 0, 0, 0], (1, 2, 1)), rot_tangents=np.zeros((1, 2, 4)),
                           bind_idx=np.zeros((g, 1), np.int64), bind_w=np.ones((g, 1)), **extra)
    means = np.array([[-0.6, 0.0, 0.0], [0.0, 0.0, 0.0], [0.6, 0.0, 0.0]])
    gs = bio.GaussianArrays(means=means, quats=np.tile([1.0, 0, 0, 0], (g, 1)),
                            log_scales=np.log(np.full((g, 3), 0.15)),
                            opacity_logits=np.log(OPACITY / (1 - OPACITY)), sh=np.zeros((g, 1, 3)))
    bio.save_bundle(path, bio.new_scene(FS, FE, 24.0, list(cameras)), nodes, gs)
    return bio.load_bundle(path)


def expected_opacity(b, frame) -> np.ndarray:
    """The engine's opacity of every Gaussian at scene ``frame`` (bundle time map)."""
    t = float(bio.time_of_frame(b.scene, frame))
    op = b.gaussians.opacities.astype(np.float64)
    life = b.nodes.gauss_lifespan
    if life is None:
        return op
    z = np.divide(t - b.nodes.gauss_t_center, life, out=np.zeros(len(op)), where=life > 0)
    return op * np.exp(-0.5 * z ** 2)


ALPHA_MIN = 1.0 / 255.0  # the engine's alpha threshold (engine/raster)
ICO_VERTICES = 42  # the ellipsoid preview's ico-sphere (subdivision 2)


def visible(opacity) -> np.ndarray:
    """The opacities the preview keeps, in order: those at or over :data:`ALPHA_MIN`."""
    opacity = np.asarray(opacity)
    return opacity[opacity >= ALPHA_MIN]


def _realized_opacity(obj, dg) -> np.ndarray:
    """Blender < 4.5 exposes no instance attributes: realize the instances in a temporary
    modifier and read one value per instance (Realize Instances copies an instance's
    attribute onto every point of its mesh)."""
    tree = bpy.data.node_groups.new("TestRealize", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    real = tree.nodes.new("GeometryNodeRealizeInstances")
    tree.links.new(gin.outputs["Geometry"], real.inputs["Geometry"])
    tree.links.new(real.outputs["Geometry"], gout.inputs["Geometry"])
    mod = obj.modifiers.new("TestRealize", "NODES")
    mod.node_group = tree
    try:
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()
        me = obj.evaluated_get(dg).data
        attr = me.attributes["ms_opacity"]
        assert attr.domain == "POINT"
        vals = np.empty(len(me.vertices), np.float32)
        attr.data.foreach_get("value", vals)
    finally:
        obj.modifiers.remove(mod)
        bpy.data.node_groups.remove(tree)
    per = vals.reshape(-1, ICO_VERTICES)  # instance-major, one ico-sphere each
    assert (per == per[:, :1]).all()
    return per[:, 0]


def evaluated_opacity(obj) -> np.ndarray:
    """``ms_opacity`` of the preview's evaluated points (POINTS) or instances (ELLIPSOIDS)."""
    dg = bpy.context.evaluated_depsgraph_get()
    if hasattr(obj, "evaluated_geometry"):  # Blender 4.5+
        geo = obj.evaluated_get(dg).evaluated_geometry()
        pc = geo.pointcloud if geo.pointcloud is not None else geo.instances_pointcloud()
        attr = pc.attributes["ms_opacity"]
        vals = np.empty(len(pc.points), np.float32)
        attr.data.foreach_get("value", vals)
        return vals
    if obj["ms_preview"] == "ELLIPSOIDS":
        return _realized_opacity(obj, dg)
    for inst in dg.object_instances:  # Blender 4.2-4.4: the point cloud is an instance
        if inst.is_instance and inst.parent is not None and inst.parent.original == obj \
                and inst.object.type == "POINTCLOUD":
            pc = inst.object.data
            vals = np.empty(len(pc.points), np.float32)
            pc.attributes["ms_opacity"].data.foreach_get("value", vals)
            return vals
    raise AssertionError("no evaluated point cloud")


def _mesh_attr(mesh_obj, name) -> np.ndarray:
    attr = mesh_obj.data.attributes[name]
    vals = np.empty(len(mesh_obj.data.vertices), np.float32)
    attr.data.foreach_get("value", vals)
    return vals


@pytest.mark.parametrize("preview", ["POINTS", "ELLIPSOIDS"])
def test_opacity_follows_the_lifespan(extension, empty_scene, tmp_path, preview):
    build = extension.addon.build
    b = write_bundle(tmp_path / "b")
    res = build.build_bundle_into_scene(bpy.context, b.path, preview=preview)
    mesh = res["mesh"]
    aux = 2 if preview == "ELLIPSOIDS" else 0  # a Gaussian's aux vertices repeat its attributes
    for name, want in (("ms_t_center", T_CENTER), ("ms_lifespan", LIFESPAN)):
        np.testing.assert_array_equal(_mesh_attr(mesh, name), np.concatenate([want, np.repeat(want, aux)]))
    mod = mesh.modifiers[extension.addon.preview.GN_MODIFIER]
    inputs = {s.name: s for s in mod.node_group.interface.items_tree if s.item_type == "SOCKET"
              and s.in_out == "INPUT"}
    assert mod[inputs["Frame Start"].identifier] == FS and mod[inputs["Frame End"].identifier] == FE

    scene = bpy.context.scene
    peak = FS + float(T_CENTER[1]) * (FE - FS)  # frame 11: Gaussian 1 fully visible
    for f in (peak, peak + 1, peak + 5, FS, FE, 19.5):  # 0, 1, 5 sigmas away; ends; a subframe
        scene.frame_set(int(f), subframe=f - int(f))
        got = evaluated_opacity(mesh)
        want = expected_opacity(b, f)
        np.testing.assert_allclose(got, visible(want), atol=2e-6, err_msg=f"frame {f}")
        assert got[0] == np.float32(b.gaussians.opacities[0]), f  # always visible: factor exactly 1
    scene.frame_set(int(peak))
    got = evaluated_opacity(mesh)
    assert len(got) == 2 and abs(got[1] - b.gaussians.opacities[1]) < 1e-6  # Gaussian 2 4 sigmas away: out
    scene.frame_set(int(peak) + 5)  # Gaussian 1 5 sigmas away: left out; 2 at 1.5 sigmas: in
    np.testing.assert_allclose(evaluated_opacity(mesh), [b.gaussians.opacities[0], expected_opacity(b, peak + 5)[2]],
                               atol=2e-6)


def test_rebuild_and_blend_keep_the_lifespans(extension, empty_scene, tmp_path):
    build = extension.addon.build
    b = write_bundle(tmp_path / "b")
    res = build.build_bundle_into_scene(bpy.context, b.path, preview="POINTS")
    out = build.rebuild_preview(bpy.context, res["collection"], preview="ELLIPSOIDS", density=1.0)
    path = str(tmp_path / "l.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    name = out["mesh"].name
    bpy.ops.wm.open_mainfile(filepath=path)
    for f in (7, 11, 13):
        bpy.context.scene.frame_set(f)
        np.testing.assert_allclose(evaluated_opacity(bpy.data.objects[name]), visible(expected_opacity(b, f)),
                                   atol=2e-6)


@pytest.mark.parametrize("lifespans", ["absent", "all zero"])
def test_without_lifespans_the_preview_is_unchanged(extension, empty_scene, tmp_path, lifespans):
    build, preview = extension.addon.build, extension.addon.preview
    b = write_bundle(tmp_path / "b", lifespans=lifespans != "absent", lifespan=np.zeros(3))
    assert build.bundle_lifespans(b.nodes) is None
    for mode in preview.PREVIEW_MODES:
        res = build.build_bundle_into_scene(bpy.context, b.path, preview=mode, camera=False)
        mesh = res["mesh"]
        names = {a.name for a in mesh.data.attributes if a.name.startswith("ms_")}
        assert names == {"ms_color", "ms_opacity", "ms_scale", "ms_rot", "ms_index", "ms_center", "ms_aux"}
        tree = mesh.modifiers[preview.GN_MODIFIER].node_group
        assert not [n for n in tree.nodes if n.bl_idname == "GeometryNodeInputSceneTime"]
        inputs = [s.name for s in tree.interface.items_tree if s.item_type == "SOCKET" and s.in_out == "INPUT"]
        assert inputs == (["Geometry", "Radius Scale"] if mode == "POINTS" else ["Geometry"])
        for f in (FS, 11, FE):
            bpy.context.scene.frame_set(f)
            np.testing.assert_array_equal(evaluated_opacity(mesh), b.gaussians.opacities.astype(np.float32))


@pytest.mark.parametrize("preview", ["POINTS", "ELLIPSOIDS"])
def test_gaussians_under_the_alpha_threshold_are_left_out(extension, empty_scene, tmp_path, preview):
    """Nothing of a Gaussian under opacity 1/255 reaches the engine's image; the preview
    leaves it out too (for Cycles each one a ray passes would be a transparent bounce)."""
    build = extension.addon.build
    b = write_bundle(tmp_path / "b", lifespans=False)
    op = np.array([0.8, 0.999 * ALPHA_MIN, 1.001 * ALPHA_MIN])
    g = b.gaussians
    g.opacity_logits = np.log(op / (1 - op)).astype(np.float32)
    bio.save_bundle(tmp_path / "c", b.scene, b.nodes, g)
    res = build.build_bundle_into_scene(bpy.context, str(tmp_path / "c"), preview=preview, camera=False)
    assert len(res["mesh"].data.vertices) == 3 * (3 if preview == "ELLIPSOIDS" else 1)  # the mesh keeps all
    bpy.context.scene.frame_set(FS)
    np.testing.assert_allclose(evaluated_opacity(res["mesh"]), op[[0, 2]], rtol=1e-5)


def test_preview_modifier_needs_the_frame_range(extension, empty_scene, tmp_path):
    build, preview = extension.addon.build, extension.addon.preview
    b = write_bundle(tmp_path / "b")
    res = build.build_bundle_into_scene(bpy.context, b.path, preview="POINTS", camera=False)
    with pytest.raises(ValueError, match="frame_range"):
        preview.add_preview_modifier(res["mesh"], "POINTS")


def test_cycles_animation_render_follows_the_lifespan(extension, empty_scene, tmp_path):
    """An animation render evaluates the window per frame: Gaussian 1 (the image centre's
    columns; its neighbours stay outside them) is seen at its t_center (frame 11) and gone
    5 sigmas later (frame 16)."""
    from tests.addon._support import look_at_w2c, render_cycles_exr_animation

    W, H, f = 32, 24, 60.0
    cam = {"w2c": look_at_w2c([0.0, -4.0, 0.0]), "K": [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]],
           "width": W, "height": H, "time": 0.0}
    b = write_bundle(tmp_path / "b", cameras=[cam])
    build = extension.addon.build
    res = build.build_bundle_into_scene(bpy.context, b.path, preview="ELLIPSOIDS")
    extension.addon.render_setup.setup_render(bpy.context, res["collection"])
    render_cycles_exr_animation(bpy.context.scene, str(tmp_path / "r_"), (11, 16, 5), samples=2)
    centre = {}
    for frame in (11, 16):
        img = bpy.data.images.load(str(tmp_path / f"r_{frame:04d}.exr"))
        px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
        img.pixels.foreach_get(px)
        alpha = px.reshape(img.size[1], img.size[0], 4)[..., 3]
        # Gaussian 1 projects to the image centre, its neighbours 9 px (4 sigma) to the sides
        centre[frame] = float(alpha[H // 2 - 1:H // 2 + 1, W // 2 - 1:W // 2 + 1].mean())
    assert centre[11] > 0.3 and centre[16] < 0.01, centre  # opacity 0.6 at its peak, 4e-6 of it at 5 sigmas
