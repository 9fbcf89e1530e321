# SPDX-License-Identifier: GPL-3.0-or-later
"""Reconstruct / Resume: run ``python -m engine train`` on the scene's footage in the
background and build the result bundle into the scene when it finishes.

The clip is either the path in ``scene.motion_splats_reconstruct.clip_path`` (a dataset
folder, a video, an image folder or a clip manifest) or, when that is empty, a clip
manifest exported (``addon.exporters.write_clip_manifest``) from the active Movie Clip
and the scene camera into a job folder under the cache dir. Nothing here blocks: the job
timer (``addon.jobs``) shows progress and runs the completion callback on the main thread.
"""

from __future__ import annotations

import time
from pathlib import Path

import bpy

from ..addon import jobs, preferences
from ..addon import properties as props_mod
from ..addon.bridge import EngineProcess

JOB_KIND = "train"

#: preferences.onnx_models() key -> engine flag
ONNX_FLAGS = {"tokens": "--tokens-model", "depth": "--depth-model",
              "segmentation": "--mask-model", "tracker": "--tracks-model"}


def reconstruct_settings(context):
    """``scene.motion_splats_result`` (clip path, preset, steps, last bundle), or None."""
    return props_mod.settings(context)


def active_movieclip(context):
    """The Movie Clip to reconstruct: the Clip editor's, else the scene's active clip, else the only one."""
    space = getattr(context, "space_data", None)
    clip = getattr(space, "clip", None) if space is not None else None
    if clip is None:
        clip = context.scene.active_clip
    if clip is None and len(bpy.data.movieclips) == 1:
        clip = bpy.data.movieclips[0]
    return clip


def new_job_dir(context) -> Path:
    """A fresh folder under the cache dir for one reconstruction."""
    base = preferences.cache_dir(context, create=True) / "jobs"
    stamp = time.strftime("%Y%m%d-%H%M%S")
    scene = bpy.path.clean_name(context.scene.name)
    out = base / f"{scene}-{stamp}"
    n = 1
    while out.exists():
        n += 1
        out = base / f"{scene}-{stamp}-{n}"
    out.mkdir(parents=True)
    return out


def train_args(clip: str, bundle: str, preset: str, *, resume: bool = False, steps: int = 0,
               device: str = "auto", models: dict | None = None, overwrite: bool = False) -> list[str]:
    """Arguments after ``python -m engine train --jsonl`` (pure; unit-tested)."""
    args = [str(clip), "--out", str(bundle), "--preset", preset]
    if resume:
        args.append("--resume")
    elif overwrite:
        args.append("--overwrite")
    if steps and steps > 0:
        args += ["--steps", str(int(steps))]
    if device and device != "auto":
        args += ["--device", device]
    for key, flag in ONNX_FLAGS.items():
        path = (models or {}).get(key)
        if path:
            args += [flag, str(path)]
    return args


def _on_complete(scene_name: str):
    """Completion callback: build the bundle into the scene it was started from."""

    def done(job):
        if job.state != "finished":
            return
        bundle = (job.result or {}).get("bundle") or job.process.argv[job.process.argv.index("--out") + 1]
        scene = bpy.data.scenes.get(scene_name) or bpy.context.scene
        result = getattr(scene, props_mod.SCENE_ATTR, None)
        density, preview, with_rig = 1.0, "POINTS", True
        if result is not None:
            density, preview, with_rig = result.density, result.preview, result.with_rig
        from ..addon.build import build_bundle_into_scene

        ctx = bpy.context
        if ctx.scene != scene:
            with ctx.temp_override(scene=scene):
                build_bundle_into_scene(bpy.context, bundle, density=density, preview=preview, with_rig=with_rig)
        else:
            build_bundle_into_scene(ctx, bundle, density=density, preview=preview, with_rig=with_rig)
        if result is not None:
            result.bundle_path = str(bundle)

    return done


def start_training(op, context, *, resume: bool):
    """Shared body of Reconstruct and Resume; returns the operator's result set."""
    settings = reconstruct_settings(context)
    if settings is None:
        op.report({"ERROR"}, "Motion Splats is not registered in this scene")
        return {"CANCELLED"}
    python = preferences.engine_python_or_report(context, op)
    if not python:
        return {"CANCELLED"}
    if resume:
        bundle = bpy.path.abspath(settings.bundle_path) if settings.bundle_path else ""
        clip = bpy.path.abspath(settings.last_clip) if settings.last_clip else ""
        if not bundle or not Path(bundle).is_dir():
            op.report({"ERROR"}, "Nothing to resume: run Reconstruct first")
            return {"CANCELLED"}
        if not clip or not Path(clip).exists():
            op.report({"ERROR"}, f"The clip of the last run is missing: {clip or '(none)'}")
            return {"CANCELLED"}
        preset = settings.last_preset or settings.preset
    else:
        preset = settings.preset
        clip = bpy.path.abspath(settings.clip_path) if settings.clip_path else ""
        if clip and not Path(clip).exists():
            op.report({"ERROR"}, f"Clip not found: {clip}")
            return {"CANCELLED"}
        try:
            job_dir = new_job_dir(context)
        except OSError as exc:
            op.report({"ERROR"}, f"Cannot create a job folder in the cache dir: {exc}")
            return {"CANCELLED"}
        if not clip:
            movieclip = active_movieclip(context)
            if movieclip is None:
                op.report({"ERROR"}, "No footage: set a clip path, or import footage as a Movie Clip first")
                return {"CANCELLED"}
            from ..addon.exporters import write_clip_manifest
            from ..engine.errors import EngineError

            try:
                write_clip_manifest(job_dir / "clip.json", context.scene, movieclip,
                                    with_cameras=settings.use_scene_camera)
            except (EngineError, OSError, ValueError) as exc:
                op.report({"ERROR"}, f"Cannot export the clip manifest: {exc}")
                return {"CANCELLED"}
            clip = str(job_dir / "clip.json")
        bundle = str(job_dir / "bundle")
    args = train_args(clip, bundle, preset, resume=resume, steps=settings.steps,
                      device=preferences.device(context), models=preferences.onnx_models(context))
    process = EngineProcess.for_engine(python, "train", args)
    label = "Resume" if resume else "Reconstruct"
    job = jobs.start(JOB_KIND, process, label=label, on_complete=_on_complete(context.scene.name))
    settings.bundle_path = bundle
    settings.last_clip = clip
    settings.last_preset = preset
    if job.state == "failed":
        op.report({"ERROR"}, " ".join(job.error_summary()))
        return {"CANCELLED"}
    op.report({"INFO"}, f"{label}: training {Path(clip).name} into {bundle}")
    return {"FINISHED"}


class _TrainBase:
    @classmethod
    def poll(cls, context):
        if reconstruct_settings(context) is None:
            return False
        if jobs.running(JOB_KIND):
            cls.poll_message_set("A reconstruction is already running")
            return False
        if jobs.running("finetune"):
            cls.poll_message_set("A fine-tune is running: wait for it or cancel it")
            return False
        return True


class MOTIONSPLATS_OT_reconstruct(_TrainBase, bpy.types.Operator):
    """Reconstruct the footage (clip path, or the active Movie Clip + scene camera) in the background
    and build the result into the scene when it finishes"""

    bl_idname = "motion_splats.reconstruct"
    bl_label = "Reconstruct"
    bl_options = {"REGISTER"}

    def execute(self, context):
        return start_training(self, context, resume=False)


class MOTIONSPLATS_OT_resume(_TrainBase, bpy.types.Operator):
    """Continue the last reconstruction from its checkpoint (after Cancel)"""

    bl_idname = "motion_splats.resume"
    bl_label = "Resume"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if not super().poll(context):
            return False
        settings = reconstruct_settings(context)
        if not settings.bundle_path:
            cls.poll_message_set("Nothing to resume: run Reconstruct first")
            return False
        return True

    def execute(self, context):
        return start_training(self, context, resume=True)


CLASSES = (MOTIONSPLATS_OT_reconstruct, MOTIONSPLATS_OT_resume)
