# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Result" panel: build a result bundle into the scene, send edits back, export."""

from __future__ import annotations

import bpy

from ..addon import build, properties


class MOTIONSPLATS_PT_result(bpy.types.Panel):
    bl_label = "Result"
    bl_idname = "MOTIONSPLATS_PT_result"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Motion Splats"

    def draw(self, context):
        layout = self.layout
        s = properties.settings(context)
        col = layout.column(align=True)
        if s is not None:
            col.prop(s, "density", slider=True)
            col.prop(s, "preview", expand=True)
            col.prop(s, "with_rig")
        op = col.operator("motion_splats.import_bundle", icon="IMPORT")
        if s is not None:
            op.density, op.preview, op.with_rig = s.density, s.preview, s.with_rig
        coll = build.bundle_collection(context)
        box = layout.box()
        if coll is None:
            box.label(text=build.why_no_result(context), icon="INFO")
        else:
            box.label(text=coll.name, icon="OUTLINER_COLLECTION")
            box.label(text=str(coll.get("ms_bundle", "")))
            moving, total = len(build.moving_nodes(coll)), len(build.node_empties(coll))
            box.operator("motion_splats.select_moving_nodes", icon="RESTRICT_SELECT_OFF",
                         text=f"Select Moving Nodes ({moving}/{total})")
            box.label(text="Colours show in Material Preview / Rendered shading", icon="SHADING_TEXTURE")
            box.operator("motion_splats.set_preview", icon="FILE_REFRESH")
            box.operator("motion_splats.setup_render", icon="RESTRICT_RENDER_OFF")
            box.operator("motion_splats.send_edits", icon="EXPORT")
            row = box.row(align=True)
            if s is not None:
                row.prop(s, "finetune_steps", text="Steps")
            row.operator("motion_splats.finetune", icon="SHADING_TEXTURE")
            box.operator("motion_splats.export_ply", icon="POINTCLOUD_DATA")
        col = layout.column(align=True)
        col.label(text="Engine inputs")
        col.operator("motion_splats.export_camera_path", icon="CAMERA_DATA")
        col.operator("motion_splats.export_clip_manifest", icon="SEQUENCE")


CLASSES = (MOTIONSPLATS_PT_result,)
