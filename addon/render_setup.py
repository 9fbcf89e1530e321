# SPDX-License-Identifier: GPL-3.0-or-later
"""Set up render: the one explicit step that makes a built result render like the engine.

Building a result never changes the scene's render settings; this step does, and
returns every change it made as a line for the operator's report (the operator is an
undo step, so Ctrl+Z takes it all back):

* the result's camera becomes the scene camera, with its resolution and pixel aspect;
* the frame range and rate of the result's clip;
* Cycles (the ellipsoid preview is built for it), enough transparent bounces for
  stacked splats, and no Russian roulette over the first :data:`MIN_TRANSPARENT_BOUNCES`
  of them (past its minimum Cycles ends paths at random, weighting the survivors, which turns
  the splats' partial transparency into noise: docs/benchmarks.md, *Cycles vs engine*);
* colour management that shows the engine's display-referred sRGB colours as they
  are: view transform Standard, look None, exposure 0, gamma 1, display sRGB;
* a black world, the background the engine composites its renders over;
* other renderable objects in the view layer (the factory Cube, ...) hidden from render.
"""

from __future__ import annotations

import bpy

from . import build

#: Cycles transparent bounces: splats stack hundreds deep along a ray.
TRANSPARENT_BOUNCES = 1024
#: Cycles minimum transparent bounces (no Russian roulette before): measured on the demo's
#: frame 16, 16 samples, 0 / 16 / 64 / 128 / 256 gave 24.90 / 25.57 / 26.26 / 26.55 / 26.74 dB
#: against the engine's render in 24 / 26 / 41 / 58 / 69 s; 64 buys most of it.
MIN_TRANSPARENT_BOUNCES = 64
#: Object types that would cover the splats in a render.
RENDERABLE = ("MESH", "CURVE", "SURFACE", "META", "FONT", "VOLUME", "POINTCLOUD", "CURVES", "GPENCIL",
              "GREASEPENCIL")


def result_camera(collection):
    """The camera built for a result collection (None when the bundle has no cameras)."""
    return next((o for o in collection.objects if o.type == "CAMERA" and "ms_camera" in o), None)


def _change(changes: list, what: str, before, after) -> None:
    if before != after:
        changes.append(f"{what}: {before} -> {after}")


def _set(changes, owner, attr: str, value, what: str) -> None:
    before = getattr(owner, attr)
    if before != value:
        setattr(owner, attr, value)
        _change(changes, what, before, value)


def setup_render(context, collection, ellipsoids: bool = True, hide_others: bool = True) -> list[str]:
    """Make ``context.scene`` render ``collection`` from its reconstructed camera.

    Returns
    -------
    list of str, one line per setting changed (``"view transform: AgX -> Standard"``).
    """
    scene, changes = context.scene, []
    cam = result_camera(collection)
    if cam is not None:
        before = scene.camera.name if scene.camera else "none"
        scene.camera = cam
        _change(changes, "camera", before, cam.name)
        r = scene.render
        for attr, key in (("resolution_x", "ms_res_x"), ("resolution_y", "ms_res_y"),
                          ("pixel_aspect_x", "ms_pixel_aspect_x"), ("pixel_aspect_y", "ms_pixel_aspect_y")):
            if key in cam:
                _set(changes, r, attr, type(getattr(r, attr))(cam[key]), attr.replace("_", " "))
        _set(changes, r, "resolution_percentage", 100, "resolution %")
    if "ms_time" in collection:
        before = (scene.frame_start, scene.frame_end, round(scene.render.fps / scene.render.fps_base, 4))
        build.apply_scene_time(scene, {"time": dict(collection["ms_time"])})
        after = (scene.frame_start, scene.frame_end, round(scene.render.fps / scene.render.fps_base, 4))
        _change(changes, "frames, fps", before, after)
    _set(changes, scene.render, "engine", "CYCLES", "render engine")
    cy = getattr(scene, "cycles", None)
    if cy is not None:
        _set(changes, cy, "transparent_max_bounces", max(cy.transparent_max_bounces, TRANSPARENT_BOUNCES),
             "transparent bounces")
        _set(changes, cy, "min_transparent_bounces",
             max(cy.min_transparent_bounces, MIN_TRANSPARENT_BOUNCES), "min transparent bounces")
    vs, ds = scene.view_settings, scene.display_settings
    _set(changes, ds, "display_device", "sRGB", "display device")
    _set(changes, vs, "view_transform", "Standard", "view transform")
    _set(changes, vs, "look", "None", "look")
    _set(changes, vs, "exposure", 0.0, "exposure")
    _set(changes, vs, "gamma", 1.0, "gamma")
    changes += _black_world(scene)
    if hide_others:
        keep = set(collection.all_objects)
        hidden = [o for o in context.view_layer.objects
                  if o.type in RENDERABLE and o not in keep and not o.hide_render]
        for o in hidden:
            o.hide_render = True
        if hidden:
            changes.append("hidden from render: " + ", ".join(sorted(o.name for o in hidden)))
    if ellipsoids and collection.get("ms_preview") != "ELLIPSOIDS":
        with_rig = any("ms_rig" in o for o in collection.objects)
        build.rebuild_preview(context, collection, density=float(collection.get("ms_density", 1.0)),
                              with_rig=with_rig, preview="ELLIPSOIDS")
        changes.append("preview: points -> ellipsoids (what Cycles renders)")
    return changes


def _black_world(scene) -> list[str]:
    world = scene.world
    if world is None:
        world = scene.world = bpy.data.worlds.new("MotionSplatsWorld")
        changes = ["world: none -> MotionSplatsWorld (black)"]
    else:
        changes = []
    before = tuple(round(c, 4) for c in world.color)
    world.color = (0.0, 0.0, 0.0)
    if world.node_tree is not None:  # a node world's Background node wins over world.color
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                col = node.inputs["Color"]
                if not col.is_linked and tuple(col.default_value[:3]) != (0.0, 0.0, 0.0):
                    before = tuple(round(c, 4) for c in col.default_value[:3])
                    col.default_value = (0.0, 0.0, 0.0, 1.0)
    _change(changes, "world colour", before, (0.0, 0.0, 0.0))
    return changes
