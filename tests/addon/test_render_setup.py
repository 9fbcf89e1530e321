"""Issue #18.3: building a result leaves the render settings alone; Set Up Render is the one
explicit, reported, undoable step that makes it render from the reconstructed camera."""

from __future__ import annotations

import bpy

from tests.addon._support import clean_jobs, registered, user_dir  # noqa: F401
from tests.addon.test_build_bundle import make_bundle


def _factory_like_scene():
    """What a new file has: a Cube, a Camera (the scene camera), AgX, 8 transparent bounces, grey world."""
    scene = bpy.context.scene
    mesh = bpy.data.meshes.new("Cube")
    mesh.from_pydata([(-1, -1, -1), (1, -1, -1), (1, 1, -1)], [], [(0, 1, 2)])
    cube = bpy.data.objects.new("Cube", mesh)
    scene.collection.objects.link(cube)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.engine = "BLENDER_EEVEE_NEXT" if bpy.app.version < (5, 0, 0) else "BLENDER_EEVEE"
    scene.view_settings.view_transform = "AgX"
    scene.cycles.transparent_max_bounces = 8
    scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
    scene.world = bpy.data.worlds.new("World")
    scene.world.color = (0.05, 0.05, 0.05)
    return scene, cube, cam


def test_build_leaves_render_settings_alone(extension, empty_scene, tmp_path):
    scene, cube, cam = _factory_like_scene()
    extension.addon.build.build_bundle_into_scene(bpy.context, make_bundle(tmp_path / "b").path)
    assert scene.view_settings.view_transform == "AgX"
    assert scene.cycles.transparent_max_bounces == 8
    assert scene.cycles.min_transparent_bounces == 0
    assert (scene.render.resolution_x, scene.render.resolution_y) == (1920, 1080)
    assert scene.camera == cam and not cube.hide_render


def test_setup_render_makes_the_result_renderable(extension, registered, tmp_path):
    scene, cube, cam = _factory_like_scene()
    res = extension.addon.build.build_bundle_into_scene(bpy.context, make_bundle(tmp_path / "b").path)
    col = res["collection"]
    bpy.context.view_layer.objects.active = res["camera"]
    assert bpy.ops.motion_splats.setup_render.poll()
    assert "UNDO" in extension.operators.result_ops.MOTIONSPLATS_OT_setup_render.bl_options
    assert bpy.ops.motion_splats.setup_render() == {"FINISHED"}
    assert scene.camera == res["camera"] and scene.camera.name == "MotionSplats_b_Camera"
    assert (scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage) == (320, 240, 100)
    assert scene.render.engine == "CYCLES"
    assert scene.view_settings.view_transform == "Standard" and scene.view_settings.look == "None"
    assert scene.cycles.transparent_max_bounces >= 1024
    assert scene.cycles.min_transparent_bounces >= 64  # no Russian-roulette noise through the splats
    assert tuple(scene.world.color) == (0.0, 0.0, 0.0)
    assert cube.hide_render  # the factory Cube no longer hides the splats
    assert col["ms_preview"] == "ELLIPSOIDS"
    mesh = next(o for o in col.objects if "ms_gaussians" in o)
    assert not mesh.hide_render and not res["camera"].hide_render
    # the report lists what changed
    changes = extension.addon.render_setup.setup_render(bpy.context, col)
    assert changes == []  # a second run has nothing left to change
