"""View-bound Gaussians in the Blender preview (addon/build.py, addon/preview.py).

A Gaussian with ``gauss_view_angle > 0`` (per-frame detail, engine/train/shot_detail.py) is
seen from a camera centre ``c`` with opacity ``opacity · exp(−½ (sin(a) / angle)²)``, ``a`` the
angle at it between the ray from ``gauss_view_origin`` and the ray from ``c``. The preview
stores the direction from the origin on each point and the material applies the fade with the
ray it is rendered along, so Cycles shows it from its own camera and not from another.
"""

from __future__ import annotations

import numpy as np
import pytest

import bpy

from engine import bundle as bio

FS, FE = 1, 2
W, H, F = 32, 24, 60.0
MEANS = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])  # Gaussian 0 plain, Gaussian 1 view-bound
EYE_OWN, EYE_OTHER = np.array([0.0, -4.0, 0.0]), np.array([2.3, -3.3, 0.0])  # ~35 degrees apart


def write_bundle(path, view=True):
    from tests.addon._support import look_at_w2c

    g = len(MEANS)
    kt = np.array([0.0, 1.0], np.float32)
    extra = {}
    if view:
        extra = {"gauss_view_origin": np.tile(EYE_OWN, (g, 1)).astype(np.float32),
                 "gauss_view_angle": np.array([0.0, 0.02], np.float32)}
    nodes = bio.NodeArrays(centers=np.zeros((1, 3)), radii=np.ones(1), key_times=kt,
                           pos_keys=np.zeros((1, 2, 3)), pos_tangents=np.zeros((1, 2, 3)),
                           rot_keys=np.tile([1.0, 0, 0, 0], (1, 2, 1)), rot_tangents=np.zeros((1, 2, 4)),
                           bind_idx=np.zeros((g, 1), np.int64), bind_w=np.ones((g, 1)), **extra)
    op = np.array([0.9, 0.9])
    gs = bio.GaussianArrays(means=MEANS, quats=np.tile([1.0, 0, 0, 0], (g, 1)),
                            log_scales=np.log(np.full((g, 3), 0.12)),
                            opacity_logits=np.log(op / (1 - op)), sh=np.zeros((g, 1, 3)))
    K = [[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]]
    cams = [{"w2c": look_at_w2c(list(eye)), "K": K, "width": W, "height": H, "time": t}
            for eye, t in ((EYE_OWN, 0.0), (EYE_OTHER, 1.0))]
    bio.save_bundle(path, bio.new_scene(FS, FE, 24.0, cams), nodes, gs)
    return bio.load_bundle(path)


def _evaluated_points(obj, name):
    dg = bpy.context.evaluated_depsgraph_get()
    if not hasattr(obj, "evaluated_geometry"):
        pytest.skip("reading evaluated point attributes needs Blender 4.5+")
    geo = obj.evaluated_get(dg).evaluated_geometry()
    pc = geo.pointcloud if geo.pointcloud is not None else geo.instances_pointcloud()
    attr = pc.attributes[name]
    width = 3 if attr.data_type == "FLOAT_VECTOR" else 1
    vals = np.empty(len(pc.points) * width, np.float32)
    attr.data.foreach_get("vector" if width == 3 else "value", vals)
    return vals.reshape(len(pc.points), width)


def test_points_carry_the_direction_from_their_seed_camera(extension, empty_scene, tmp_path):
    build = extension.addon.build
    b = write_bundle(tmp_path / "b")
    res = build.build_bundle_into_scene(bpy.context, b.path, preview="POINTS", camera=False)
    mesh = res["mesh"]
    assert {"ms_view_origin", "ms_view_angle"} <= {a.name for a in mesh.data.attributes}
    want = MEANS - EYE_OWN
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    np.testing.assert_allclose(_evaluated_points(mesh, "ms_view_dir"), want, atol=1e-6)
    np.testing.assert_allclose(_evaluated_points(mesh, "ms_view_angle")[:, 0], [0.0, 0.02], atol=1e-7)


def test_without_view_binding_there_are_no_view_attributes(extension, empty_scene, tmp_path):
    build = extension.addon.build
    b = write_bundle(tmp_path / "b", view=False)
    assert build.bundle_view_binding(b.nodes) is None
    res = build.build_bundle_into_scene(bpy.context, b.path, preview="ELLIPSOIDS", camera=False)
    names = {a.name for a in res["mesh"].data.attributes}
    assert "ms_view_origin" not in names and "ms_view_angle" not in names
    mat = res["mesh"].data.materials[0]
    assert not [n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeAttribute"
                and n.attribute_name.startswith("ms_view")]


def test_cycles_shows_view_bound_detail_from_its_own_camera_only(extension, empty_scene, tmp_path):
    """Frame 1 renders from the Gaussians' seed camera, frame 2 from 35 degrees away: the
    plain Gaussian is seen in both, the view-bound one only in frame 1."""
    import torch

    from engine.geometry.camera import project
    from tests.addon._support import look_at_w2c, render_cycles_exr_animation

    b = write_bundle(tmp_path / "b")
    build = extension.addon.build
    res = build.build_bundle_into_scene(bpy.context, b.path, preview="ELLIPSOIDS")
    extension.addon.render_setup.setup_render(bpy.context, res["collection"])
    render_cycles_exr_animation(bpy.context.scene, str(tmp_path / "r_"), (FS, FE, 1), samples=4)
    K = torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=torch.float64)
    alpha_at = {}
    for frame, eye in ((FS, EYE_OWN), (FE, EYE_OTHER)):
        img = bpy.data.images.load(str(tmp_path / f"r_{frame:04d}.exr"))
        px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
        img.pixels.foreach_get(px)
        alpha = px.reshape(img.size[1], img.size[0], 4)[::-1, :, 3]  # Blender's rows go bottom-up
        uv, _ = project(K, torch.tensor(look_at_w2c(list(eye)), dtype=torch.float64),
                        torch.tensor(MEANS, dtype=torch.float64))
        cols, rows = np.floor(uv[:, 0].numpy()).astype(int), np.floor(uv[:, 1].numpy()).astype(int)
        alpha_at[frame] = [float(alpha[r - 1:r + 1, c - 1:c + 1].mean()) for r, c in zip(rows, cols)]
    assert alpha_at[FS][0] > 0.3 and alpha_at[FS][1] > 0.3, alpha_at  # both from the seed camera
    assert alpha_at[FE][0] > 0.3 and alpha_at[FE][1] < 0.02, alpha_at  # the detail fades 35 degrees away
