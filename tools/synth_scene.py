"""Synthetic dynamic-scene generator (Nerfies/HyperNeRF "vrig" layout + ground truth).

Runs with the project venv, where ``bpy`` is importable::

    .venv/bin/python tools/synth_scene.py --out DIR [--preset tiny|small] [--frames N]
        [--width W] [--height H] [--seed S] [--kind rigid|articulated|nonrigid|all]

or from Python: ``generate_scene(out_dir, preset='tiny', ...) -> Path``.

The engine never imports this module (it imports ``bpy``); benchmarks run it as a
subprocess. See ``docs/synthetic_scenes.md`` for the output layout and conventions.

Rendering: Cycles on the CPU with unlit (emission) materials, so images are free of
sampling noise and identical in both views apart from geometry. Ground truth (z-depth
and object index) comes from a second 1-sample render with a material override whose
emission is ``(View Z Depth, Object Index, 0)``, written as 32-bit float EXR and read
back through ``bpy.data.images``; a box pixel filter of width 0.01 puts that single
sample at the pixel centre, so GT depth is exact at continuous pixel ``(u+0.5, v+0.5)``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script: the engine's geometry (numpy/torch, no bpy) is one home
    sys.path.insert(0, str(REPO))

PRESETS = {
    "tiny": dict(frames=12, width=96, height=72, rgb_samples=2, points_per_object=200),
    "small": dict(frames=48, width=240, height=180, rgb_samples=4, points_per_object=500),
}

# object ids (also Blender pass_index; 0 = static background)
OBJECT_IDS = {"background": 0, "rigid_cube": 1, "arm_base": 2, "arm_upper": 3, "arm_fore": 4, "flag": 5,
              "ball": 6, "swing_upper": 7, "swing_fore": 8}
KIND_OBJECTS = {
    "rigid": ["rigid_cube"],
    "articulated": ["arm_base", "arm_upper", "arm_fore"],
    "nonrigid": ["flag"],
    # large motion: a ball rolling (and bouncing) across most of the frame and a fast two-link
    # pendulum whose tip sweeps ~2 units: objects crossing a third of the frame or more
    "large": ["ball", "swing_upper", "swing_fore"],
}
KIND_OBJECTS["all"] = KIND_OBJECTS["rigid"] + KIND_OBJECTS["articulated"] + KIND_OBJECTS["nonrigid"]
BALL_RADIUS = 0.35

SCENE_TARGET = np.array([0.0, 0.0, 0.9])
VAL_BASELINE = 0.8  # val camera centre = train centre + 0.8 * train +x axis (~15% of the ~5.3 distance)


# ----------------------------------------------------------------------------- cameras

def _look_at_w2c(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera 4x4 (x right, y down, z forward), float64: the engine's
    :func:`engine.geometry.camera.look_at` (world up +z)."""
    import torch

    from engine.geometry.camera import look_at

    return look_at(torch.as_tensor(eye, dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64)).numpy()


def camera_path(frames: int, seed: int):
    """Train and val w2c [F,4,4] (OpenCV) for a smooth handheld-like arc."""
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * np.pi, size=8)
    az0 = rng.uniform(-0.3, 0.3)
    t = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    w2c_train = np.zeros((frames, 4, 4))
    w2c_val = np.zeros((frames, 4, 4))
    for i, ti in enumerate(t):
        az = az0 - 0.6 + 1.2 * ti + 0.03 * math.sin(2 * np.pi * 1.7 * ti + ph[0])
        radius = 5.2 + 0.15 * math.sin(2 * np.pi * 1.3 * ti + ph[1])
        height = 1.7 + 0.12 * math.sin(2 * np.pi * 2.1 * ti + ph[2])
        eye = np.array([radius * math.sin(az), -radius * math.cos(az), height])
        eye += 0.02 * np.array([math.sin(2 * np.pi * 3.1 * ti + ph[3]),
                                math.sin(2 * np.pi * 2.9 * ti + ph[4]),
                                math.sin(2 * np.pi * 3.7 * ti + ph[5])])
        target = SCENE_TARGET + 0.08 * np.array([math.sin(2 * np.pi * 1.1 * ti + ph[6]),
                                                 0.0, math.sin(2 * np.pi * 0.9 * ti + ph[7])])
        w2c = _look_at_w2c(eye, target)
        w2c_train[i] = w2c
        off = np.eye(4)  # val = rigid offset in the train camera frame: x_val = x_train - b
        off[0, 3] = -VAL_BASELINE
        w2c_val[i] = off @ w2c
    return t, w2c_train, w2c_val


def intrinsics(width: int, height: int) -> np.ndarray:
    f = 1.0 * width
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- motion

def object_transforms(name: str, ti: float, seed: int) -> np.ndarray:
    """4x4 local-to-parent matrix of an animated object at engine time ti (pure numpy)."""
    rng = np.random.default_rng(seed + 1000 + OBJECT_IDS[name])
    ph = rng.uniform(0, 2 * np.pi)

    def trs(loc, rz=0.0, rx=0.0, ry=0.0, scale=(1, 1, 1)):
        cz, sz, cx, sx, cy, sy = math.cos(rz), math.sin(rz), math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
        Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        M = np.eye(4)
        M[:3, :3] = Rz @ Ry @ Rx @ np.diag(scale)
        M[:3, 3] = loc
        return M

    if name == "rigid_cube":
        x = -1.6 + 1.2 * ti
        y = 0.6 + 0.3 * math.sin(2 * np.pi * ti + ph)
        z = 0.55 + 0.25 * math.sin(2 * np.pi * 1.5 * ti)
        return trs((x, y, z), rz=1.6 * ti + ph, rx=0.9 * ti, scale=(0.4, 0.4, 0.4))
    if name == "arm_base":  # turntable rotating about z
        return trs((1.3, 0.3, 0.25), rz=0.8 * math.sin(2 * np.pi * 0.7 * ti + ph))
    if name == "arm_upper":  # hinge about local x at the top of the base
        return trs((0.0, 0.0, 0.25), rx=0.9 * math.sin(2 * np.pi * ti + ph))
    if name == "arm_fore":  # hinge at the top of the upper arm
        return trs((0.0, 0.0, 0.9), rx=-0.3 - 0.8 * math.sin(2 * np.pi * 1.3 * ti + ph))
    if name == "flag":
        return trs((-0.2, -0.6, 1.2), rx=math.pi / 2, rz=0.2 + 0.3 * ti)
    if name == "ball":  # rolls along x over ~3.6 units (no slip: angle = distance / radius), two bounces
        x = -1.9 + 3.6 * ti
        z = -0.1 + BALL_RADIUS + 0.45 * abs(math.sin(2 * np.pi * ti + 0.3 * ph))
        return trs((x, 0.5 + 0.2 * math.sin(np.pi * ti + ph), z), ry=(x + 1.9) / BALL_RADIUS)
    if name == "swing_upper":  # pendulum hung from a fixed pivot in the air, swinging +-1.1 rad
        return trs((0.6, -0.5, 2.1), ry=1.1 * math.sin(2 * np.pi * 1.2 * ti + ph))
    if name == "swing_fore":  # hinged at the end of the upper link, faster and wider
        return trs((0.0, 0.0, -0.9), ry=1.3 * math.sin(2 * np.pi * 2.0 * ti + 0.5 * ph))
    raise KeyError(name)


# ----------------------------------------------------------------------------- bpy scene

def _bpy():
    import bpy  # noqa: WPS433 - only the generator needs Blender
    return bpy


def _use_nodes(idblock):
    # deprecated (always on) in Blender 5.x; still needed to create the default tree
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        idblock.use_nodes = True


def _textured_material(bpy, name: str, seed: int, scale: float, coords: str, tint):
    """Unlit high-frequency procedural texture: noise x checker x voronoi, fake facing shade."""
    mat = bpy.data.materials.new(name)
    _use_nodes(mat)
    nt = mat.node_tree
    nt.nodes.clear()
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mapping = nt.nodes.new("ShaderNodeMapping")
    rng = np.random.default_rng(seed)
    mapping.inputs["Location"].default_value = tuple(rng.uniform(-10, 10, 3))
    mapping.inputs["Scale"].default_value = (scale, scale, scale)
    nt.links.new(tc.outputs[coords], mapping.inputs["Vector"])
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 3.0
    noise.inputs["Detail"].default_value = 6.0
    nt.links.new(mapping.outputs["Vector"], noise.inputs["Vector"])
    checker = nt.nodes.new("ShaderNodeTexChecker")
    checker.inputs["Scale"].default_value = 4.0
    checker.inputs["Color1"].default_value = (*tint, 1.0)
    checker.inputs["Color2"].default_value = (tint[0] * 0.35, tint[1] * 0.35, tint[2] * 0.35, 1.0)
    nt.links.new(mapping.outputs["Vector"], checker.inputs["Vector"])
    vor = nt.nodes.new("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 9.0
    nt.links.new(mapping.outputs["Vector"], vor.inputs["Vector"])
    mix1 = nt.nodes.new("ShaderNodeMix")
    mix1.data_type = "RGBA"
    mix1.blend_type = "MULTIPLY"
    mix1.inputs["Factor"].default_value = 0.8
    nt.links.new(checker.outputs["Color"], mix1.inputs["A"])
    nt.links.new(noise.outputs["Color"], mix1.inputs["B"])
    mix2 = nt.nodes.new("ShaderNodeMix")
    mix2.data_type = "RGBA"
    mix2.blend_type = "OVERLAY"
    mix2.inputs["Factor"].default_value = 0.5
    nt.links.new(mix1.outputs["Result"], mix2.inputs["A"])
    nt.links.new(vor.outputs["Color"], mix2.inputs["B"])
    lw = nt.nodes.new("ShaderNodeLayerWeight")
    lw.inputs["Blend"].default_value = 0.5
    shade = nt.nodes.new("ShaderNodeMath")
    shade.operation = "MULTIPLY_ADD"
    nt.links.new(lw.outputs["Facing"], shade.inputs[0])
    shade.inputs[1].default_value = -0.5
    shade.inputs[2].default_value = 1.0
    mix3 = nt.nodes.new("ShaderNodeMix")
    mix3.data_type = "RGBA"
    mix3.blend_type = "MULTIPLY"
    mix3.inputs["Factor"].default_value = 1.0
    nt.links.new(mix2.outputs["Result"], mix3.inputs["A"])
    nt.links.new(shade.outputs["Value"], mix3.inputs["B"])
    em = nt.nodes.new("ShaderNodeEmission")
    nt.links.new(mix3.outputs["Result"], em.inputs["Color"])
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    return mat


def _gt_material(bpy):
    """Emission = (camera z-depth, object pass index, 0)."""
    mat = bpy.data.materials.new("GT_override")
    _use_nodes(mat)
    nt = mat.node_tree
    nt.nodes.clear()
    cam = nt.nodes.new("ShaderNodeCameraData")
    info = nt.nodes.new("ShaderNodeObjectInfo")
    comb = nt.nodes.new("ShaderNodeCombineXYZ")
    nt.links.new(cam.outputs["View Z Depth"], comb.inputs["X"])
    nt.links.new(info.outputs["Object Index"], comb.inputs["Y"])
    em = nt.nodes.new("ShaderNodeEmission")
    nt.links.new(comb.outputs["Vector"], em.inputs["Color"])
    em.inputs["Strength"].default_value = 1.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    return mat


def _add_box(bpy, name, size, loc, mat, parent=None):
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0))
    ob = bpy.context.active_object
    ob.name = name
    me = ob.data
    # bake size/offset into the mesh so the object origin is the hinge
    for v in me.vertices:
        v.co = (v.co[0] * size[0] + loc[0], v.co[1] * size[1] + loc[1], v.co[2] * size[2] + loc[2])
    me.materials.append(mat)
    if parent is not None:
        ob.parent = parent
    return ob


def build_scene(bpy, kind: str, seed: int, width: int, height: int):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    objs = {}
    # static room: inward-visible box (Cycles renders back faces) so every ray hits something
    room_mat = _textured_material(bpy, "room", seed + 1, 0.6, "Object", (0.85, 0.8, 0.7))
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0))
    room = bpy.context.active_object
    room.name = "background"
    for v in room.data.vertices:
        v.co = (v.co[0] * 16.0, v.co[1] * 16.0, v.co[2] * 8.0 + 3.9)
    room.data.materials.append(room_mat)
    objs["background"] = room

    wanted = KIND_OBJECTS[kind]
    if "rigid_cube" in wanted:
        m = _textured_material(bpy, "cube", seed + 2, 1.5, "Generated", (0.9, 0.3, 0.2))
        objs["rigid_cube"] = _add_box(bpy, "rigid_cube", (1, 1, 1), (0, 0, 0), m)
    if "arm_base" in wanted:
        m = _textured_material(bpy, "arm", seed + 3, 2.0, "Generated", (0.2, 0.5, 0.9))
        base = _add_box(bpy, "arm_base", (0.6, 0.6, 0.5), (0, 0, 0), m)
        upper = _add_box(bpy, "arm_upper", (0.25, 0.25, 0.9), (0, 0, 0.45), m, parent=base)
        fore = _add_box(bpy, "arm_fore", (0.2, 0.2, 0.7), (0, 0, 0.35), m, parent=upper)
        objs.update(arm_base=base, arm_upper=upper, arm_fore=fore)
    if "flag" in wanted:
        m = _textured_material(bpy, "flag", seed + 4, 1.0, "UV", (0.3, 0.85, 0.3))
        bpy.ops.mesh.primitive_grid_add(x_subdivisions=24, y_subdivisions=16, size=1.0, location=(0, 0, 0))
        flag = bpy.context.active_object
        flag.name = "flag"
        for v in flag.data.vertices:
            v.co = (v.co[0] * 1.4, v.co[1] * 1.0, 0.0)
        flag.data.materials.append(m)
        wave = flag.modifiers.new("wave", "WAVE")
        wave.use_normal = False  # displace along local z
        wave.height = 0.18
        wave.width = 0.6
        wave.narrowness = 1.0
        wave.speed = 0.06
        wave.time_offset = 0.0
        wave.start_position_x = -0.7
        wave.use_y = False
        objs["flag"] = flag

    if "ball" in wanted:
        m = _textured_material(bpy, "ball", seed + 5, 2.5, "Generated", (0.95, 0.75, 0.15))
        bpy.ops.mesh.primitive_uv_sphere_add(segments=32, ring_count=16, radius=BALL_RADIUS, location=(0, 0, 0))
        ball = bpy.context.active_object
        ball.name = "ball"
        ball.data.materials.append(m)
        objs["ball"] = ball
    if "swing_upper" in wanted:
        m = _textured_material(bpy, "swing", seed + 6, 2.0, "Generated", (0.75, 0.25, 0.85))
        upper = _add_box(bpy, "swing_upper", (0.22, 0.22, 0.9), (0, 0, -0.45), m)
        fore = _add_box(bpy, "swing_fore", (0.18, 0.18, 0.8), (0, 0, -0.4), m, parent=upper)
        objs.update(swing_upper=upper, swing_fore=fore)

    for name, ob in objs.items():
        ob.pass_index = OBJECT_IDS[name]

    cams = {}
    for cname in ("train", "val"):
        cd = bpy.data.cameras.new(cname)
        cd.sensor_fit = "HORIZONTAL"
        cd.sensor_width = 36.0
        cd.lens = intrinsics(width, height)[0, 0] * 36.0 / width
        cd.shift_x = cd.shift_y = 0.0
        cd.clip_start = 0.05
        cd.clip_end = 100.0
        ob = bpy.data.objects.new(cname, cd)
        scene.collection.objects.link(ob)
        cams[cname] = ob

    world = bpy.data.worlds.new("world")
    _use_nodes(world)
    bg = world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world

    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = False
    r.use_persistent_data = True
    scene.cycles.device = "CPU"
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.seed = seed
    scene.cycles.max_bounces = 0
    scene.cycles.transparent_max_bounces = 0
    scene.cycles.use_auto_tile = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    return scene, objs, cams


def _set_frame(bpy, scene, objs, frame: int, ti: float, seed: int):
    from mathutils import Matrix
    scene.frame_set(frame)
    for name, ob in objs.items():
        if name == "background":
            continue
        ob.matrix_parent_inverse = Matrix.Identity(4)
        ob.matrix_basis = Matrix(object_transforms(name, ti, seed).tolist())
    bpy.context.view_layer.update()


def _set_camera(scene, cam_ob, w2c_cv: np.ndarray):
    from mathutils import Matrix

    from engine.geometry.blender_camera import blender_matrix_from_w2c

    cam_ob.matrix_world = Matrix(blender_matrix_from_w2c(w2c_cv).tolist())
    scene.camera = cam_ob


def _read_exr(bpy, path: Path, width: int, height: int) -> np.ndarray:
    img = bpy.data.images.load(str(path))
    px = np.empty(width * height * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(height, width, 4)[::-1]  # Blender stores rows bottom-up


def _sample_surface(bpy, objs, names, n_per_object: int, seed: int):
    """(name, tri_vertex_indices [n,3], barycentric [n,3]) on the evaluated mesh."""
    rng = np.random.default_rng(seed + 77)
    dg = bpy.context.evaluated_depsgraph_get()
    out = []
    for name in names:
        ob = objs[name].evaluated_get(dg)
        me = ob.to_mesh()
        me.calc_loop_triangles()
        nv = len(me.vertices)
        co = np.empty(nv * 3, dtype=np.float64)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3)
        tris = np.empty(len(me.loop_triangles) * 3, dtype=np.int64)
        me.loop_triangles.foreach_get("vertices", tris)
        tris = tris.reshape(-1, 3)
        ob.to_mesh_clear()
        a, b, c = co[tris[:, 0]], co[tris[:, 1]], co[tris[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        n = n_per_object * (2 if name == "background" else 1)
        idx = rng.choice(len(tris), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
        out.append((name, tris[idx], bary))
    return out


def _eval_points(bpy, objs, samples):
    dg = bpy.context.evaluated_depsgraph_get()
    res = []
    for name, tri, bary in samples:
        ob = objs[name].evaluated_get(dg)
        me = ob.to_mesh()
        co = np.empty(len(me.vertices) * 3, dtype=np.float64)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3)
        M = np.array(ob.matrix_world)
        ob.to_mesh_clear()
        local = np.einsum("nk,nkc->nc", bary, co[tri])
        res.append(local @ M[:3, :3].T + M[:3, 3])
    return np.concatenate(res, axis=0)


def _write_png(path: Path, img: np.ndarray):
    import cv2
    if img.ndim == 3:
        img = img[..., ::-1]
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")


def _nerfies_camera(w2c: np.ndarray, K: np.ndarray, width: int, height: int) -> dict:
    R = w2c[:3, :3]
    return {
        "orientation": R.tolist(),
        "position": (-R.T @ w2c[:3, 3]).tolist(),
        "focal_length": float(K[0, 0]),
        "pixel_aspect_ratio": float(K[1, 1] / K[0, 0]),
        "principal_point": [float(K[0, 2]), float(K[1, 2])],
        "skew": 0.0,
        "radial_distortion": [0.0, 0.0, 0.0],
        "tangential_distortion": [0.0, 0.0],
        "image_size": [int(width), int(height)],
    }


def generate_scene(out_dir, preset: str = "tiny", frames: int | None = None, width: int | None = None,
                   height: int | None = None, seed: int = 0, kind: str = "all", verbose: bool = False) -> Path:
    """Render a synthetic dynamic scene into ``out_dir`` and return it (see docs/synthetic_scenes.md)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}")
    if kind not in KIND_OBJECTS:
        raise ValueError(f"unknown kind {kind!r}")
    cfg = dict(PRESETS[preset])
    F = int(frames or cfg["frames"])
    W = int(width or cfg["width"])
    H = int(height or cfg["height"])
    if W % 2 or H % 2:
        raise ValueError("width and height must be even (rgb/2x is a 2x2 box downscale)")
    out = Path(out_dir)
    for sub in ("camera", "rgb/1x", "rgb/2x", "gt/depth", "gt/mask", "gt/object_id"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    bpy = _bpy()
    scene, objs, cams = build_scene(bpy, kind, seed, W, H)
    gt_mat = _gt_material(bpy)
    times, w2c_train, w2c_val = camera_path(F, seed)
    K = intrinsics(W, H)

    names = ["background"] + [n for n in KIND_OBJECTS[kind]]
    _set_frame(bpy, scene, objs, 1, 0.0, seed)
    samples = _sample_surface(bpy, objs, names, cfg["points_per_object"], seed)
    object_id = np.concatenate([np.full(len(s[1]), OBJECT_IDS[s[0]], np.int32) for s in samples])
    points = np.zeros((len(object_id), F, 3), dtype=np.float64)

    ids, train_ids, val_ids, metadata = [], [], [], {}
    depth_min, depth_max = np.inf, 0.0
    vl = scene.view_layers[0]
    tmp = Path(tempfile.mkdtemp(prefix="synth_"))
    try:
        for f in range(F):
            _set_frame(bpy, scene, objs, f + 1, float(times[f]), seed)
            points[:, f] = _eval_points(bpy, objs, samples)
            for cam_name, w2c_all, prefix, cam_id in (("train", w2c_train, "left", 0), ("val", w2c_val, "right", 1)):
                iid = f"{prefix}_{f:06d}"
                _set_camera(scene, cams[cam_name], w2c_all[f])
                # RGB
                vl.material_override = None
                scene.cycles.samples = cfg["rgb_samples"]
                scene.cycles.pixel_filter_type = "BLACKMAN_HARRIS"
                scene.cycles.filter_width = 1.5
                scene.render.image_settings.file_format = "PNG"
                scene.render.image_settings.color_mode = "RGB"
                scene.render.image_settings.color_depth = "8"
                scene.render.filepath = str(out / "rgb" / "1x" / f"{iid}.png")
                bpy.ops.render.render(write_still=True)
                # GT: depth + object index
                vl.material_override = gt_mat
                scene.cycles.samples = 1
                scene.cycles.pixel_filter_type = "BOX"
                scene.cycles.filter_width = 0.01
                scene.render.image_settings.file_format = "OPEN_EXR"
                scene.render.image_settings.color_mode = "RGBA"
                scene.render.image_settings.color_depth = "32"
                exr = tmp / f"{iid}.exr"
                scene.render.filepath = str(exr)
                bpy.ops.render.render(write_still=True)
                gt = _read_exr(bpy, exr, W, H)
                depth = gt[..., 0].astype(np.float32)
                oid = np.rint(gt[..., 1]).astype(np.uint8)
                np.save(out / "gt" / "depth" / f"{iid}.npy", np.ascontiguousarray(depth))
                _write_png(out / "gt" / "object_id" / f"{iid}.png", np.ascontiguousarray(oid))
                _write_png(out / "gt" / "mask" / f"{iid}.png", np.ascontiguousarray((oid > 0).astype(np.uint8) * 255))
                depth_min, depth_max = min(depth_min, float(depth.min())), max(depth_max, float(depth.max()))
                with open(out / "camera" / f"{iid}.json", "w") as fh:
                    json.dump(_nerfies_camera(w2c_all[f], K, W, H), fh, indent=2)
                metadata[iid] = {"warp_id": f, "appearance_id": f, "camera_id": cam_id, "time_id": f}
                ids.append(iid)
                (train_ids if cam_id == 0 else val_ids).append(iid)
                if verbose:
                    print(f"[synth] {iid} {time.time() - t0:.1f}s", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    import cv2
    for iid in ids:
        img = cv2.imread(str(out / "rgb" / "1x" / f"{iid}.png"), cv2.IMREAD_COLOR)
        small = img.reshape(H // 2, 2, W // 2, 2, 3).astype(np.float32).mean(axis=(1, 3))
        cv2.imwrite(str(out / "rgb" / "2x" / f"{iid}.png"), np.rint(small).astype(np.uint8))

    def dump(name, obj):
        with open(out / name, "w") as fh:
            json.dump(obj, fh, indent=2)

    dump("dataset.json", {"count": len(ids), "num_exemplars": len(train_ids), "ids": ids,
                          "train_ids": train_ids, "val_ids": val_ids})
    dump("metadata.json", metadata)
    dump("scene.json", {"scale": 1.0, "center": [0.0, 0.0, 0.0],
                        "near": round(0.9 * depth_min, 4), "far": round(1.1 * depth_max, 4)})
    dump("gt/objects.json", {"object_ids": {n: OBJECT_IDS[n] for n in names},
                             "kind": kind, "seed": seed, "frames": F, "width": W, "height": H,
                             "preset": preset, "val_baseline": VAL_BASELINE})
    Ks = np.repeat(K[None], F, axis=0)
    np.savez(out / "gt" / "cameras.npz", K=Ks.astype(np.float64), w2c_train=w2c_train, w2c_val=w2c_val,
             times=times.astype(np.float64))
    np.savez(out / "gt" / "trajectories.npz", points=points.astype(np.float32),
             is_dynamic=object_id > 0, object_id=object_id)
    if verbose:
        print(f"[synth] done {out} in {time.time() - t0:.1f}s", flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--preset", default="tiny", choices=sorted(PRESETS))
    p.add_argument("--frames", type=int)
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--kind", default="all", choices=sorted(KIND_OBJECTS))
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    out = generate_scene(a.out, a.preset, a.frames, a.width, a.height, a.seed, a.kind, verbose=not a.quiet)
    print(json.dumps({"out": str(out)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
