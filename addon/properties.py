# SPDX-License-Identifier: GPL-3.0-or-later
"""Scene settings of the result builder (``scene.motion_splats_result``)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

SCENE_ATTR = "motion_splats_result"
PRESET_ITEMS = (("preview", "Preview", "Minutes on a laptop CPU (the default)"),
                ("standard", "Standard", "More Gaussians and steps"),
                ("high", "High", "Best quality; slow without a GPU"))
SOURCE_ITEMS = (("MOVIE_CLIP", "Movie Clip", "Reconstruct the active Movie Clip (Import Footage), with the scene "
                 "camera when it moves"),
                ("PATH", "Clip Path", "Reconstruct a dataset folder, video, image folder or clip manifest read by "
                 "the engine itself"))
PREVIEW_ITEMS = (("POINTS", "Points", "Fast point cloud preview (viewport, Eevee, Cycles)"),
                 ("ELLIPSOIDS", "Ellipsoids", "Oriented 3σ ellipsoids with a Gaussian falloff (Cycles)"))


def _clip_path_changed(self, _context):
    # Typing a path is choosing it: the panel then shows "Clip Path" as the source.
    if self.clip_path:
        self.source = "PATH"


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
    source: EnumProperty(name="Source", default="MOVIE_CLIP", items=SOURCE_ITEMS,
                         description="What Reconstruct reads: one input, never a silent fallback to the other")
    clip_path: StringProperty(name="Clip", subtype="FILE_PATH", update=_clip_path_changed,
                              description="Footage the engine reads itself: a dataset folder, video, image folder "
                              "or clip manifest (setting it switches Source to Clip Path)")
    output_dir: StringProperty(name="Results", subtype="DIR_PATH", default="//MotionSplats",
                               description="Folder for reconstruction results, one sub-folder per clip. Relative "
                               "paths are beside the .blend; an unsaved file uses the add-on preferences' folder")
    preset: EnumProperty(name="Preset", default="preview", items=PRESET_ITEMS)
    steps: IntProperty(name="Steps", default=0, min=0, description="Training steps (0: the preset's default, raised to 10 per frame for a long clip)")
    use_scene_camera: BoolProperty(name="Use Scene Camera", default=True,
                                   description="Send the scene camera's animation as the footage's cameras when "
                                   "it moves (a camera that does not move is never sent: the engine solves the "
                                   "cameras). Off: the engine always solves them")
    last_clip: StringProperty(name="Last Clip", subtype="FILE_PATH", options={"HIDDEN"},
                              description="Clip the last reconstruction trained on (for Resume)")
    last_preset: StringProperty(name="Last Preset", options={"HIDDEN"})
    last_steps: IntProperty(name="Last Steps", default=0, min=0, options={"HIDDEN"},
                            description="Steps of the last reconstruction (Resume continues that very run)")
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
