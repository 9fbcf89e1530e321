"""Building a result bundle into the scene (addon/build.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import bpy

from tests.addon._support import fcurves_of
from engine import bundle as bio
from engine.geometry.binding import bind_gaussians
from engine.geometry.dualquat import deform_points, dq_apply_rotations, dq_blend, node_transforms_dq
from engine.geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_eval_quat
from engine.geometry.quaternion import quat_from_axis_angle

SCALE = 2.0
FS, FE = 1, 25


def make_bundle(path, n=50, g=2000, k=5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    centers = (torch.rand(n, 3, generator=gen, dtype=f64) - 0.5) * 2 * SCALE
    radii = torch.full((n,), 0.6, dtype=f64)
    means = centers[torch.randint(0, n, (g,), generator=gen)] + 0.3 * torch.randn(g, 3, generator=gen, dtype=f64)
    idx, w = bind_gaussians(means, centers, radii, 4)
    kt = torch.linspace(0, 1, k, dtype=f64)
    pos = centers[:, None] + 0.3 * torch.randn(n, k, 3, generator=gen, dtype=f64)
    ang = (0.5 * torch.randn(n, k, generator=gen, dtype=f64)).clamp(-1.2, 1.2)
    rot = quat_from_axis_angle(torch.randn(n, k, 3, generator=gen, dtype=f64), ang)
    rot = torch.where(rot[..., :1] < 0, -rot, rot)
    nodes = bio.NodeArrays(centers=centers.numpy(), radii=radii.numpy(), key_times=kt.numpy(),
                           pos_keys=pos.numpy(), pos_tangents=catmull_rom_tangents(kt, pos).numpy(),
                           rot_keys=rot.numpy(), rot_tangents=catmull_rom_tangents(kt, rot).numpy(),
                           bind_idx=idx.numpy(), bind_w=w.numpy())
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(g, 4))
    gauss = bio.GaussianArrays(means=means.numpy(), quats=quats / np.linalg.norm(quats, axis=1, keepdims=True),
                               log_scales=np.log(rng.uniform(0.02, 0.08, (g, 3))),
                               opacity_logits=rng.normal(size=g), sh=rng.normal(size=(g, 1, 3)))
    cams = []
    for j, t in enumerate(np.linspace(0, 1, 4)):
        a = 0.3 * j
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = [0.1 * j, -0.2, 8.0]
        cams.append({"w2c": w2c, "K": [[300.0, 0, 161.0], [0, 300.0, 118.0], [0, 0, 1]], "width": 320,
                     "height": 240, "time": float(t)})
    scene = bio.new_scene(FS, FE, 24.0, cams)
    bio.save_bundle(path, scene, nodes, gauss)
    return bio.load_bundle(path)


@pytest.fixture()
def bundle(tmp_path):
    return make_bundle(tmp_path / "bundle")


def engine_state(b, frame, keep=None):
    n = b.nodes
    t = torch.tensor([(frame - FS) / (FE - FS)], dtype=torch.float64)
    kt = torch.as_tensor(n.key_times, dtype=torch.float64)
    tin = (lambda a: None if a is None else torch.as_tensor(a, dtype=torch.float64))
    p = hermite_eval(kt, torch.as_tensor(n.pos_keys, dtype=torch.float64),
                     torch.as_tensor(n.pos_tangents, dtype=torch.float64), t, tin(n.pos_tangents_in))[:, 0]
    q = hermite_eval_quat(kt, torch.as_tensor(n.rot_keys, dtype=torch.float64),
                          torch.as_tensor(n.rot_tangents, dtype=torch.float64), t, tin(n.rot_tangents_in))[:, 0]
    keep = np.arange(b.gaussians.count) if keep is None else keep
    c = torch.as_tensor(n.centers, dtype=torch.float64)
    idx, w = torch.as_tensor(n.bind_idx[keep]), torch.as_tensor(n.bind_w[keep], dtype=torch.float64)
    x = torch.as_tensor(b.gaussians.means[keep], dtype=torch.float64)
    pts = deform_points(c, p, q, idx, w, x).numpy()
    dq = dq_blend(node_transforms_dq(c, p, q), idx, w)
    rots = dq_apply_rotations(dq, torch.as_tensor(b.gaussians.quats[keep], dtype=torch.float64)).numpy()
    return p.numpy(), q.numpy(), pts, rots


def _evaluated_points_legacy(obj, dg):
    """:func:`evaluated_points` from ``depsgraph.object_instances`` (Blender 4.2-4.4)."""
    pcs, mats = [], []
    for inst in dg.object_instances:
        if not inst.is_instance or inst.parent is None or inst.parent.original != obj:
            continue
        if inst.object.type == "POINTCLOUD":
            co = np.empty(len(inst.object.data.points) * 3, np.float32)
            inst.object.data.attributes["position"].data.foreach_get("vector", co)
            pcs.append(co.reshape(-1, 3))
        else:
            mats.append((inst.persistent_id[0], np.array(inst.matrix_world, np.float32).T))
    if pcs:
        return pcs[0], None
    mats.sort(key=lambda item: item[0])
    return np.stack([m for _, m in mats]), None


def evaluated_points(obj):
    """World positions of the preview's points (POINTS) or instances (ELLIPSOIDS)."""
    dg = bpy.context.evaluated_depsgraph_get()
    if not hasattr(obj, "evaluated_geometry"):  # Blender < 4.5: read the depsgraph's instances
        return _evaluated_points_legacy(obj, dg)
    geo = obj.evaluated_get(dg).evaluated_geometry()
    pc = geo.pointcloud
    if pc is not None:
        co = np.empty(len(pc.points) * 3, np.float32)
        attr = pc.attributes["position"]
        attr.data.foreach_get("vector", co)
        return co.reshape(-1, 3), None
    inst = geo.instances_pointcloud()
    m = np.empty(len(inst.points) * 16, np.float32)
    inst.attributes["instance_transform"].data.foreach_get("value", m)
    m = m.reshape(-1, 4, 4)
    return m, inst


def test_build_points(extension, empty_scene, bundle):
    build = extension.addon.build
    res = build.build_bundle_into_scene(bpy.context, bundle.path, preview="POINTS")
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end, scene.render.fps) == (FS, FE, 24)
    empties = res["empties"]
    n = bundle.nodes
    assert len(empties) == n.count == len(build.node_empties(res["collection"]))
    # F-curves reproduce the splines at the keys
    frames = FS + n.key_times * (FE - FS)
    for i in (0, 17, 49):
        fcs = fcurves_of(empties[i])
        for c in range(3):
            fc = fcs.find("location", index=c)
            got = [fc.evaluate(f) for f in frames]
            np.testing.assert_allclose(got, n.pos_keys[i, :, c], atol=1e-5)
        for c in range(4):
            fc = fcs.find("rotation_quaternion", index=c)
            np.testing.assert_allclose([fc.evaluate(f) for f in frames], n.rot_keys[i, :, c], atol=1e-5)
    mesh = res["mesh"]
    assert [m.type for m in mesh.modifiers] == ["ARMATURE", "NODES"]
    # attributes
    attrs = mesh.data.attributes
    g = bundle.gaussians.count
    col = np.empty(g * 4, np.float32)
    attrs["ms_color"].data.foreach_get("color", col)
    # stored linearised: Blender shades in linear light (sRGB view transform on output)
    np.testing.assert_allclose(col.reshape(-1, 4)[:, :3], build.srgb_to_linear(bundle.gaussians.colors), atol=1e-6)
    op = np.empty(g, np.float32)
    attrs["ms_opacity"].data.foreach_get("value", op)
    np.testing.assert_allclose(op, bundle.gaussians.opacities, atol=1e-6)
    sc = np.empty(g * 3, np.float32)
    attrs["ms_scale"].data.foreach_get("vector", sc)
    np.testing.assert_allclose(sc.reshape(-1, 3), np.exp(bundle.gaussians.log_scales), rtol=1e-5)
    q = np.empty(g * 4, np.float32)
    attrs["ms_rot"].data.foreach_get("value", q)
    np.testing.assert_allclose(q.reshape(-1, 4), bundle.gaussians.quats, atol=1e-6)
    # evaluated positions follow the engine's deform
    for f in (1, 8, 19.5):
        scene.frame_set(int(f), subframe=f - int(f))
        pts, _ = evaluated_points(mesh)
        assert pts.shape == (g, 3)
        _, _, ref, _ = engine_state(bundle, f)
        assert np.abs(pts - ref).max() <= 1e-4 * SCALE, f


def test_build_ellipsoids_density(extension, empty_scene, bundle):
    build = extension.addon.build
    res = build.build_bundle_into_scene(bpy.context, bundle.path, preview="ELLIPSOIDS", density=0.25)
    mesh = res["mesh"]
    keep = build.subset_indices(bundle.gaussians.count, 0.25)
    assert res["gaussians"] == len(keep) == 500
    assert len(mesh.data.vertices) == 3 * len(keep)
    assert [m.type for m in mesh.modifiers] == ["ARMATURE", "NODES"]
    idx = np.empty(len(mesh.data.vertices), np.int32)
    mesh.data.attributes["ms_index"].data.foreach_get("value", idx)
    np.testing.assert_array_equal(idx[:len(keep)], keep)
    scene = bpy.context.scene
    for f in (1, 13, 22.25):
        scene.frame_set(int(f), subframe=f - int(f))
        m, _ = evaluated_points(mesh)
        assert m.shape == (len(keep), 4, 4)
        _, _, ref_pts, ref_rot = engine_state(bundle, f, keep)
        mt = m.transpose(0, 2, 1)  # Blender stores column-major
        assert np.abs(mt[:, :3, 3] - ref_pts).max() <= 1e-4 * SCALE
        sig = np.exp(bundle.gaussians.log_scales[keep])
        want = build.quat_to_matrix(ref_rot) * sig[:, None, :]
        assert np.abs(mt[:, :3, :3] - want).max() <= 1e-3 * sig.max(), f


def test_camera_matches_bundle(extension, empty_scene, bundle):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    build = extension.addon.build
    res = build.build_bundle_into_scene(bpy.context, bundle.path, with_rig=False)
    scene, cam = bpy.context.scene, res["camera"]
    assert scene.camera == cam  # an empty scene had none
    extension.addon.render_setup.setup_render(bpy.context, res["collection"], ellipsoids=False)  # resolution
    X = np.array([0.3, -0.4, 0.5])
    for c in bundle.scene["cameras"]:
        f = bio.frame_of_time(bundle.scene, c["time"])
        scene.frame_set(int(f), subframe=float(f - int(f)))
        K, w2c = np.array(c["K"]), np.array(c["w2c"])
        xc = w2c[:3, :3] @ X + w2c[:3, 3]
        uv = (K @ xc)[:2] / xc[2]
        v = world_to_camera_view(scene, cam, Vector(X))
        got = np.array([v.x * c["width"], (1 - v.y) * c["height"]])
        assert np.abs(got - uv).max() < 0.5, (got, uv)


def test_blend_roundtrip_and_render(extension, empty_scene, bundle, tmp_path):
    build = extension.addon.build
    res = build.build_bundle_into_scene(bpy.context, bundle.path, preview="ELLIPSOIDS", density=0.1)
    keep = build.subset_indices(bundle.gaussians.count, 0.1)
    path = str(tmp_path / "b.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    name = res["mesh"].name
    bpy.ops.wm.open_mainfile(filepath=path)
    scene = bpy.context.scene
    scene.frame_set(13)
    m, _ = evaluated_points(bpy.data.objects[name])
    _, _, ref, _ = engine_state(bundle, 13, keep)
    assert np.abs(m.transpose(0, 2, 1)[:, :3, 3] - ref).max() <= 1e-4 * SCALE
    # tiny Cycles render through the bundle camera
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 2
    scene.render.resolution_x, scene.render.resolution_y = 64, 48
    scene.render.film_transparent = True
    scene.render.filepath = str(tmp_path / "r.png")
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(tmp_path / "r.png"))
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    assert px.reshape(-1, 4)[:, 3].max() > 0.05


@pytest.mark.xfail(bpy.app.version < (5, 0, 0), strict=True,
                   reason="Blender 4.2 Cycles: 3 of ~1500 pixels off by up to 0.005 in alpha (99th percentile "
                   "9e-5); 5.0 meets the 0.002 bound everywhere")
def test_ellipsoid_alpha_is_gaussian_along_the_ray(extension, empty_scene, tmp_path):
    """Cycles alpha of one ellipsoid = opacity · exp(−½ d²), d = Mahalanobis distance of the pixel ray."""
    build = extension.addon.build
    sig = np.array([0.5, 0.3, 0.2])
    a = np.deg2rad(30) / 2
    q = np.array([np.cos(a), 0.3 * np.sin(a), 0.0, np.sqrt(0.91) * np.sin(a)])  # some tilted rotation
    opacity, color = 0.8, np.array([0.2, 0.6, 0.9])
    kt = np.array([0.0, 1.0], np.float32)
    nodes = bio.NodeArrays(centers=np.zeros((1, 3)), radii=np.ones(1), key_times=kt,
                           pos_keys=np.zeros((1, 2, 3)), pos_tangents=np.zeros((1, 2, 3)),
                           rot_keys=np.tile([1.0, 0, 0, 0], (1, 2, 1)), rot_tangents=np.zeros((1, 2, 4)),
                           bind_idx=np.zeros((1, 1), np.int64), bind_w=np.ones((1, 1)))
    gs = bio.GaussianArrays(means=np.zeros((1, 3)), quats=q[None], log_scales=np.log(sig)[None],
                            opacity_logits=[np.log(opacity / (1 - opacity))],
                            sh=((color - 0.5) / bio.SH_C0)[None, None])
    W, H, f = 64, 48, 150.0
    w2c = np.eye(4)
    w2c[2, 3] = 8.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    cam = {"w2c": w2c, "K": K, "width": W, "height": H, "time": 0.0}
    bio.save_bundle(tmp_path / "b", bio.new_scene(1, 2, 24, [cam]), nodes, gs)
    res = build.build_bundle_into_scene(bpy.context, tmp_path / "b", preview="ELLIPSOIDS")
    extension.addon.render_setup.setup_render(bpy.context, res["collection"])  # camera resolution, Standard view
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.cycles.filter_width = 0.01
    scene.cycles.use_denoising = False
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = str(tmp_path / "r.exr")
    scene.frame_set(1)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(tmp_path / "r.exr"))
    px = np.empty(W * H * 4, np.float32)
    img.pixels.foreach_get(px)
    rgba = px.reshape(H, W, 4)[::-1]  # Blender images are bottom-up
    # expected alpha per pixel centre
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(u - W / 2) / f, (v - H / 2) / f, np.ones_like(u)], -1)  # camera = world axes
    o = np.array([0.0, 0.0, -8.0])
    Rm = build.quat_to_matrix(q)
    p = (Rm.T @ o) / sig
    vv = (d @ Rm) / sig
    d2 = (p ** 2).sum() - (vv @ p) ** 2 / (vv ** 2).sum(-1)
    want = np.where(d2 < 9, np.minimum(opacity * np.exp(-0.5 * d2), 0.99), 0.0)  # cut at 3σ
    inside = want > 0
    near_cut = np.abs(np.sqrt(d2) - 3) < 0.02  # float noise decides these pixels
    err = np.abs(rgba[..., 3] - want)[~near_cut]
    assert inside.sum() > 100 and err.max() < 0.002, err.max()
    np.testing.assert_allclose(rgba[..., :3][inside] / np.maximum(rgba[..., 3:][inside], 1e-3),
                               np.broadcast_to(extension.addon.build.srgb_to_linear(color), (inside.sum(), 3)),
                               atol=0.03)  # EXR holds linear light
