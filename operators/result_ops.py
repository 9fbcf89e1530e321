# SPDX-License-Identifier: GPL-3.0-or-later
"""Operators for result bundles: import/build, send spline edits back, exports."""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ExportHelper

from ..addon import build, exporters, properties, render_setup
from ..engine.errors import InputError


def _fail(op, exc) -> set:
    if isinstance(exc, InputError):
        msg = str(exc)
    else:
        msg = f"{type(exc).__name__}: {exc}"
    op.report({"ERROR"}, msg)
    return {"CANCELLED"}


class MOTIONSPLATS_OT_import_bundle(bpy.types.Operator):
    """Build a Motion Splats result bundle (scene.json, nodes.npz, gaussians.ply) into the scene"""

    bl_idname = "motion_splats.import_bundle"
    bl_label = "Import Result Bundle"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Bundle Folder", subtype="DIR_PATH")
    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE", "HIDDEN"})
    filter_glob: StringProperty(default="scene.json", options={"HIDDEN"})
    density: FloatProperty(name="Density", default=1.0, min=0.001, max=1.0, subtype="FACTOR")
    preview: EnumProperty(name="Preview", items=properties.PREVIEW_ITEMS, default="POINTS")
    with_rig: BoolProperty(name="Rig", default=True)

    @classmethod
    def poll(cls, context):
        return context.scene is not None and (context.mode == "OBJECT" or context.mode is None)

    def invoke(self, context, event):
        s = properties.settings(context)
        if s is not None:
            self.density, self.preview, self.with_rig = s.density, s.preview, s.with_rig
            if s.bundle_path and not self.directory:
                self.directory = s.bundle_path
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        folder = Path(bpy.path.abspath(self.directory or "")) if self.directory else Path(self.filepath).parent
        if folder.name == "scene.json":
            folder = folder.parent
        try:
            res = build.build_bundle_into_scene(context, folder, density=self.density, with_rig=self.with_rig,
                                                preview=self.preview)
        except Exception as exc:  # user-facing: never a traceback in the UI
            return _fail(self, exc)
        s = properties.settings(context)
        if s is not None:
            s.bundle_path = str(folder)
        changes = "; ".join(res["scene_changes"])
        self.report({"INFO"}, f"Built {len(res['empties'])} nodes and {res['gaussians']} Gaussians in "
                              f"{res['timings']['total']:.1f} s into '{res['collection'].name}'"
                              + (f". Scene: {changes}" if changes else ""))
        return {"FINISHED"}


class _ResultOperator:
    """Acts on the active result (:func:`addon.build.bundle_collection`); refuses when ambiguous."""

    @classmethod
    def poll(cls, context):
        if build.bundle_collection(context) is None:
            cls.poll_message_set(build.why_no_result(context))
            return False
        return True


def report_sent(op, sent) -> None:
    """One report line for :func:`exporters.send_edits`'s result."""
    if sent.path is None:
        op.report({"INFO"}, "No node was edited: nodes.npz is unchanged")
        return
    msg = (f"Sent {len(sent.edited)} edited node(s) to {sent.path}; the previous file is in {sent.backup.parent}")
    if sent.rekeyed:
        msg += (". The key frames changed: the other nodes got an exact split of their curves at the new key "
                "times (same motion, no new keys on their Empties)")
    op.report({"INFO"}, msg)


class MOTIONSPLATS_OT_send_edits(_ResultOperator, bpy.types.Operator):
    """Write the edited node Empties' F-curves into the bundle's nodes.npz (only the edited nodes change;
    the previous file is backed up into the bundle's backups folder)"""

    bl_idname = "motion_splats.send_edits"
    bl_label = "Send Edits to Bundle"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        col = build.bundle_collection(context)
        try:
            sent = exporters.send_edits(col)
        except Exception as exc:
            return _fail(self, exc)
        report_sent(self, sent)
        return {"FINISHED"}


class MOTIONSPLATS_OT_export_ply(_ResultOperator, ExportHelper, bpy.types.Operator):
    """Export the bundle's canonical Gaussians as a standard 3DGS PLY"""

    bl_idname = "motion_splats.export_ply"
    bl_label = "Export Gaussians (PLY)"
    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})

    def execute(self, context):
        try:
            count = exporters.export_ply(build.bundle_collection(context), self.filepath)
        except Exception as exc:
            return _fail(self, exc)
        self.report({"INFO"}, f"Wrote {count} Gaussians to {self.filepath}")
        return {"FINISHED"}


class MOTIONSPLATS_OT_export_camera_path(ExportHelper, bpy.types.Operator):
    """Export the scene camera's animation as a Motion Splats camera path (engine render --camera)"""

    bl_idname = "motion_splats.export_camera_path"
    bl_label = "Export Camera Path"
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        cam = context.scene.camera if context.scene else None
        return cam is not None and cam.type == "CAMERA"

    def execute(self, context):
        try:
            data = exporters.write_camera_path(self.filepath, context.scene)
        except Exception as exc:
            return _fail(self, exc)
        self.report({"INFO"}, f"Wrote {len(data['cameras'])} cameras to {self.filepath}")
        return {"FINISHED"}


#: The last items of :func:`_clip_items`. Blender keeps only pointers to the strings a
#: dynamic EnumProperty callback returns, so Python must keep them alive (else garbage
#: labels or a crash, as the EnumProperty documentation warns).
_CLIP_ITEMS: list = []


def _clip_items(self, context):
    items = [(c.name, c.name, c.filepath) for c in bpy.data.movieclips] or [("", "(no movie clips)", "")]
    if items != _CLIP_ITEMS:
        _CLIP_ITEMS[:] = items
    return _CLIP_ITEMS


class MOTIONSPLATS_OT_export_clip_manifest(ExportHelper, bpy.types.Operator):
    """Export a Movie Clip (video or image sequence) and the scene camera as a clip manifest for the engine"""

    bl_idname = "motion_splats.export_clip_manifest"
    bl_label = "Export Clip Manifest"
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})
    clip: EnumProperty(name="Clip", items=_clip_items)
    with_cameras: BoolProperty(name="Cameras", default=True,
                               description="Include the scene camera per frame when it moves (else the engine "
                               "solves them)")

    @classmethod
    def poll(cls, context):
        return len(bpy.data.movieclips) > 0

    def execute(self, context):
        clip = bpy.data.movieclips.get(self.clip) if self.clip else None
        if clip is None:
            clip = getattr(getattr(context, "space_data", None), "clip", None) or bpy.data.movieclips[0]
        from .reconstruct_ops import footage_cameras

        try:
            cams, note = footage_cameras(context, clip, self.with_cameras)  # a still camera is never sent
            m = exporters.write_clip_manifest(self.filepath, context.scene, clip, with_cameras=False, cameras=cams)
        except Exception as exc:
            return _fail(self, exc)
        self.report({"WARNING"} if cams is None and self.with_cameras else {"INFO"},
                    f"Wrote clip manifest for frames {m['frame_start']}..{m['frame_end']} "
                    f"({len(m.get('cameras') or [])} cameras) to {self.filepath}. {note}")
        return {"FINISHED"}


class MOTIONSPLATS_OT_set_preview(_ResultOperator, bpy.types.Operator):
    """Rebuild the Gaussian preview with the panel's density, preview and rig settings (keeps the node Empties)"""

    bl_idname = "motion_splats.set_preview"
    bl_label = "Rebuild Preview"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        col = build.bundle_collection(context)
        s = properties.settings(context)
        preview = s.preview if s is not None else "POINTS"
        density = s.density if s is not None else 1.0
        with_rig = s.with_rig if s is not None else True
        try:
            res = build.rebuild_preview(context, col, density=density, with_rig=with_rig, preview=preview)
        except Exception as exc:
            return _fail(self, exc)
        self.report({"INFO"}, f"Rebuilt the {preview.lower()} preview with {res['gaussians']} Gaussians "
                              "(node Empties and their edits kept)")
        return {"FINISHED"}


class MOTIONSPLATS_OT_select_moving_nodes(_ResultOperator, bpy.types.Operator):
    """Select the node Empties of the active result that move (dynamic score of the node initialisation
    >= 0.5); they are also grouped in its 'moving' sub-collection"""

    bl_idname = "motion_splats.select_moving_nodes"
    bl_label = "Select Moving Nodes"
    bl_options = {"REGISTER", "UNDO"}

    extend: BoolProperty(name="Extend", default=False, description="Keep the current selection")

    def execute(self, context):
        col = build.bundle_collection(context)
        moving = build.moving_nodes(col)
        if not self.extend:
            for obj in context.view_layer.objects:
                obj.select_set(False)
        visible = [e for e in moving if e.name in context.view_layer.objects]
        for e in visible:
            e.select_set(True)
        if visible:
            context.view_layer.objects.active = visible[0]
        self.report({"INFO"}, f"Selected {len(visible)} moving node(s) of {len(build.node_empties(col))} in "
                              f"'{col.name}'")
        return {"FINISHED"}


class MOTIONSPLATS_OT_setup_render(_ResultOperator, bpy.types.Operator):
    """Render the result like the engine: its camera as scene camera (with its resolution), Cycles with
    the ellipsoid preview, Standard colour management, a black world, other objects hidden from render.
    Every change is reported; Undo restores them"""

    bl_idname = "motion_splats.setup_render"
    bl_label = "Set Up Render"
    bl_options = {"REGISTER", "UNDO"}

    ellipsoids: BoolProperty(name="Ellipsoid Preview", default=True,
                             description="Rebuild the preview as ellipsoids, the mode made for Cycles")
    hide_others: BoolProperty(name="Hide Other Objects", default=True,
                              description="Hide renderable objects outside the result from render")

    def execute(self, context):
        col = build.bundle_collection(context)
        try:
            changes = render_setup.setup_render(context, col, self.ellipsoids, self.hide_others)
        except Exception as exc:
            return _fail(self, exc)
        self.report({"INFO"}, f"Set up render for '{col.name}': " + ("; ".join(changes) or "nothing to change"))
        return {"FINISHED"}


CLASSES = (MOTIONSPLATS_OT_import_bundle, MOTIONSPLATS_OT_setup_render, MOTIONSPLATS_OT_select_moving_nodes, MOTIONSPLATS_OT_send_edits, MOTIONSPLATS_OT_export_ply,
           MOTIONSPLATS_OT_export_camera_path, MOTIONSPLATS_OT_export_clip_manifest, MOTIONSPLATS_OT_set_preview)
