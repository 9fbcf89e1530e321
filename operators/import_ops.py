# SPDX-License-Identifier: GPL-3.0-or-later
"""Import footage (video / image sequence -> Movie Clip + scene setup) and cameras
(Blender camera solve or COLMAP model -> animated scene camera). See addon/cameras.py."""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty

from ..addon import cameras, footage
from ..addon import properties as props_mod
from ..engine.errors import EngineError


def _set_background(cam_obj, clip) -> None:
    data = cam_obj.data
    data.show_background_images = True
    bg = next((b for b in data.background_images if b.source == "MOVIE_CLIP"), None)
    if bg is None:
        bg = data.background_images.new()
    bg.source = "MOVIE_CLIP"
    bg.clip = clip
    bg.clip_user.use_render_undistorted = False
    bg.alpha = 1.0


def _scene_state(scene) -> dict:
    r = scene.render
    return {"frames": f"{scene.frame_start}-{scene.frame_end}", "fps": f"{r.fps / r.fps_base:.4g} fps",
            "resolution": f"{r.resolution_x}x{r.resolution_y} at {r.resolution_percentage}%",
            "camera": scene.camera.name if scene.camera else "none"}


def describe_changes(before: dict, after: dict) -> str:
    """``"frames 1-250 -> 1-48, fps 24 fps -> 30 fps"`` for the entries that changed ("" if none)."""
    return ", ".join(f"{k} {before[k]} -> {after[k]}" for k in before if before[k] != after[k])


def match_scene_to_clip(scene, clip) -> None:
    """Frame range, frame rate and resolution of ``scene`` from the Movie Clip."""
    w, h = int(clip.size[0]), int(clip.size[1])
    scene.frame_start = int(clip.frame_start)
    scene.frame_end = int(clip.frame_start) + max(int(clip.frame_duration), 1) - 1
    fps = float(clip.fps) if clip.fps else 0.0
    if fps > 0:
        # fps as integer / base (e.g. 29.97 = 30000 / 1001)
        if abs(fps - round(fps)) < 1e-3:
            scene.render.fps, scene.render.fps_base = int(round(fps)), 1.0
        else:
            scene.render.fps = int(round(fps * 1.001))
            scene.render.fps_base = scene.render.fps / fps
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0


def import_footage(context, filepath: str, set_background: bool = True, match_scene: bool = True):
    """Load ``filepath`` as a Movie Clip (and, with ``match_scene``, set the scene up for it); returns the clip."""
    scene = context.scene
    clip = bpy.data.movieclips.load(filepath, check_existing=True)
    w, h = int(clip.size[0]), int(clip.size[1])
    if w <= 0 or h <= 0:
        raise EngineError(f"Blender cannot read frames from {filepath}")
    scene.active_clip = clip
    if match_scene:
        match_scene_to_clip(scene, clip)
    cam = scene.camera
    if cam is None:
        data = bpy.data.cameras.new("MotionSplatsFootageCamera")
        cam = bpy.data.objects.new("MotionSplatsFootageCamera", data)
        scene.collection.objects.link(cam)
        scene.camera = cam
    if set_background and cam.type == "CAMERA":
        _set_background(cam, clip)
    return clip


class MOTIONSPLATS_OT_import_footage(bpy.types.Operator):
    """Load a video or an image sequence as a Movie Clip (and match the scene's frame range, frame rate and
    resolution to it), or choose a dataset folder / clip manifest for Reconstruct to read"""

    bl_idname = "motion_splats.import_footage"
    bl_label = "Import Footage"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"SKIP_SAVE", "HIDDEN"})
    filter_movie: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_image: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_folder: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_json: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    set_background: BoolProperty(name="Camera Background", default=True,
                                 description="Show the footage behind the active camera")
    match_scene: BoolProperty(name="Match Scene", default=True,
                              description="Set the scene's frame range, frame rate and resolution to the "
                              "footage's (reported; Undo restores them)")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        path = bpy.path.abspath(self.filepath) if self.filepath else bpy.path.abspath(self.directory)
        try:
            kind, what = footage.classify(path) if path else (None, "")
        except EngineError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if kind is None:
            self.report({"ERROR"}, "No footage chosen: pick a video, an image of a sequence or a dataset folder")
            return {"CANCELLED"}
        s = props_mod.settings(context)
        if kind not in footage.MOVIE_KINDS:
            # the engine reads it with its own cameras / splits: Reconstruct uses the path
            if s is None:
                self.report({"ERROR"}, "Motion Splats is not registered in this scene")
                return {"CANCELLED"}
            s.clip_path = path
            s.source = "PATH"
            self.report({"INFO"}, f"Reconstruct will read the {what} {path} (Source: Clip Path); the scene "
                                  "is unchanged")
            return {"FINISHED"}
        if kind == "images":
            path = str(clip_io_first_image(path))
        before = _scene_state(context.scene)
        try:
            clip = import_footage(context, path, self.set_background, self.match_scene)
        except (RuntimeError, EngineError) as exc:
            self.report({"ERROR"}, f"Cannot load {Path(path).name}: {exc}")
            return {"CANCELLED"}
        if s is not None:
            s.source = "MOVIE_CLIP"
        changes = describe_changes(before, _scene_state(context.scene))
        self.report({"INFO"}, f"Footage '{clip.name}' ({what}, {clip.size[0]}x{clip.size[1]}) is the Movie Clip "
                              f"to reconstruct. Scene: {changes or 'unchanged'}")
        return {"FINISHED"}


def clip_io_first_image(folder) -> Path:
    """The first image of an image folder (Blender loads the sequence from it)."""
    from ..engine.io.clip import list_images

    return list_images(folder)[0]


class MOTIONSPLATS_OT_import_tracking_camera(bpy.types.Operator):
    """Create an animated camera from the active Movie Clip's camera solve (Motion Tracking)"""

    bl_idname = "motion_splats.import_tracking_camera"
    bl_label = "Tracked Camera"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if context.scene.active_clip is None:
            cls.poll_message_set("No active Movie Clip: import footage first")
            return False
        return True

    def execute(self, context):
        clip = context.scene.active_clip
        try:
            cams = cameras.read_tracking_reconstruction(clip)
        except EngineError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        obj = cameras.build_animated_camera(context.scene, f"Tracked_{clip.name}", cams["K"][0], cams["width"],
                                            cams["height"], cams["w2c"], cams["frames"])
        if context.scene.camera and obj.type == "CAMERA":
            _set_background(obj, clip)
        self.report({"INFO"}, f"Camera '{obj.name}': {len(cams['frames'])} solved frames, solve error "
                              f"{cams['average_error']:.3g} px")
        return {"FINISHED"}


class MOTIONSPLATS_OT_import_colmap_camera(bpy.types.Operator):
    """Create an animated camera from a COLMAP model folder (text or binary; images in name order,
    one per frame from the scene's start frame)"""

    bl_idname = "motion_splats.import_colmap_camera"
    bl_label = "COLMAP Camera"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH", options={"SKIP_SAVE"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        folder = bpy.path.abspath(self.directory)
        if not folder or not Path(folder).is_dir():
            self.report({"ERROR"}, f"COLMAP folder not found: {folder or '(none chosen)'}")
            return {"CANCELLED"}
        try:
            cams = cameras.read_colmap_cameras(folder)
        except EngineError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        scene = context.scene
        frames = [scene.frame_start + i for i in range(len(cams["names"]))]
        if len(cams["names"]) > 1:
            scene.frame_end = frames[-1]
        obj = cameras.build_animated_camera(scene, "COLMAPCamera", cams["K"][0], cams["width"], cams["height"],
                                            cams["w2c"], frames)
        msg = f"Camera '{obj.name}': {len(frames)} images, frames {frames[0]}-{frames[-1]}"
        if cams["dist"] is not None and abs(cams["dist"]).max() > 0:
            self.report({"WARNING"}, msg + " (lens distortion ignored in the Blender camera)")
        elif not np_allclose_K(cams["K"]):
            self.report({"WARNING"}, msg + " (the images have different intrinsics; the first one is used)")
        else:
            self.report({"INFO"}, msg)
        return {"FINISHED"}


def np_allclose_K(Ks) -> bool:
    import numpy as np

    return bool(np.allclose(Ks, Ks[:1], rtol=1e-6, atol=1e-6))


CLASSES = (MOTIONSPLATS_OT_import_footage, MOTIONSPLATS_OT_import_tracking_camera,
           MOTIONSPLATS_OT_import_colmap_camera)
