# SPDX-License-Identifier: GPL-3.0-or-later
"""Scene settings of the result builder (``scene.motion_splats_result``)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, PointerProperty, StringProperty

SCENE_ATTR = "motion_splats_result"
PREVIEW_ITEMS = (("POINTS", "Points", "Fast point cloud preview (viewport, Eevee, Cycles)"),
                 ("ELLIPSOIDS", "Ellipsoids", "Oriented 3σ ellipsoids with a Gaussian falloff (Cycles)"))


class MOTIONSPLATS_PG_result(bpy.types.PropertyGroup):
    density: FloatProperty(
        name="Density", description="Fraction of the Gaussians built into the preview "
        "(a deterministic subset; the bundle and exports keep all of them)",
        default=1.0, min=0.001, max=1.0, subtype="FACTOR")
    preview: EnumProperty(name="Preview", default="POINTS", items=PREVIEW_ITEMS)
    with_rig: BoolProperty(name="Rig", default=True,
                           description="Build the armature that deforms the Gaussians with the node Empties")
    bundle_path: StringProperty(name="Bundle", subtype="DIR_PATH",
                                description="Result bundle folder last built into this scene")


def register_scene_props():
    bpy.types.Scene.motion_splats_result = PointerProperty(type=MOTIONSPLATS_PG_result)


def unregister_scene_props():
    if hasattr(bpy.types.Scene, SCENE_ATTR):
        del bpy.types.Scene.motion_splats_result


def settings(context):
    """The scene's result settings, or None when the add-on is not registered."""
    return getattr(context.scene, SCENE_ATTR, None)
