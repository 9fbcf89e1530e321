# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Reconstruct" panel: footage / camera import, clip path, preset, Reconstruct / Resume.
Progress of the running job shows in the main panel's job box."""

from __future__ import annotations

import bpy

from ..addon import properties


class _ReconstructPanel:
    """Drawn in the 3D Viewport and the Movie Clip editor sidebars."""

    bl_label = "Reconstruct"
    bl_region_type = "UI"
    bl_category = "Motion Splats"
    bl_order = 1

    def draw(self, context):
        layout = self.layout
        col = layout.column(align=True)
        col.operator("motion_splats.import_footage", icon="FILE_MOVIE")
        row = col.row(align=True)
        row.operator("motion_splats.import_tracking_camera", icon="TRACKER")
        row.operator("motion_splats.import_colmap_camera", icon="CAMERA_DATA")
        s = properties.settings(context)
        if s is None:
            return
        col = layout.column(align=True)
        col.row(align=True).prop(s, "source", expand=True)
        if s.source == "PATH":
            col.prop(s, "clip_path")
        else:
            clip = context.scene.active_clip
            col.label(text=f"Movie Clip: {clip.name}" if clip else "No Movie Clip: use Import Footage",
                      icon="FILE_MOVIE" if clip else "ERROR")
            col.prop(s, "use_scene_camera")
        col.prop(s, "preset")
        col.prop(s, "output_dir")
        header, body = layout.panel("MOTIONSPLATS_reconstruct_advanced", default_closed=True)
        header.label(text="Advanced")
        if body is not None:
            body.prop(s, "steps")
        row = layout.row(align=True)
        row.scale_y = 1.3
        row.operator("motion_splats.reconstruct", icon="PLAY")
        row.operator("motion_splats.resume", icon="FILE_REFRESH")


class MOTIONSPLATS_PT_reconstruct(_ReconstructPanel, bpy.types.Panel):
    bl_idname = "MOTIONSPLATS_PT_reconstruct"
    bl_space_type = "VIEW_3D"


class MOTIONSPLATS_PT_clip_reconstruct(_ReconstructPanel, bpy.types.Panel):
    bl_idname = "MOTIONSPLATS_PT_clip_reconstruct"
    bl_space_type = "CLIP_EDITOR"


CLASSES = (MOTIONSPLATS_PT_reconstruct, MOTIONSPLATS_PT_clip_reconstruct)
