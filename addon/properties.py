# SPDX-License-Identifier: GPL-3.0-or-later
"""Scene settings of the result builder (``scene.motion_splats_result``)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

SCENE_ATTR = "motion_splats_result"
PRESET_ITEMS = (("preview", "Preview", "Minutes on a laptop CPU (the default)"),
                ("standard", "Standard", "More Gaussians and steps"),
                ("high", "High", "Best quality; slow without a GPU"))
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
    # -- reconstruction (operators/reconstruct_ops.py) --
    clip_path: StringProperty(name="Clip", subtype="FILE_PATH",
                              description="Footage to reconstruct: a dataset folder, video, image folder or clip "
                              "manifest. Empty: export the active Movie Clip and the scene camera")
    preset: EnumProperty(name="Preset", default="preview", items=PRESET_ITEMS)
    steps: IntProperty(name="Steps", default=0, min=0, description="Training steps (0: the preset's default)")
    use_scene_camera: BoolProperty(name="Use Scene Camera", default=True,
                                   description="Send the scene camera's animation as the footage's cameras "
                                   "(off: the engine solves the cameras)")
    last_clip: StringProperty(name="Last Clip", subtype="FILE_PATH", options={"HIDDEN"},
                              description="Clip the last reconstruction trained on (for Resume)")
    last_preset: StringProperty(name="Last Preset", options={"HIDDEN"})
    # -- fine-tuning (operators/finetune_ops.py) --
    finetune_steps: IntProperty(name="Fine-tune Steps", default=200, min=1, soft_max=5000,
                                description="Optimisation steps of Fine-tune Appearance")


def register_scene_props():
    bpy.types.Scene.motion_splats_result = PointerProperty(type=MOTIONSPLATS_PG_result)


def unregister_scene_props():
    if hasattr(bpy.types.Scene, SCENE_ATTR):
        del bpy.types.Scene.motion_splats_result


def settings(context):
    """The scene's result settings, or None when the add-on is not registered."""
    return getattr(context.scene, SCENE_ATTR, None)
