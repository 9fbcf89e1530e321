# SPDX-License-Identifier: GPL-3.0-or-later
"""Reconstruct / Resume: run ``python -m engine train`` on the scene's footage in the
background and build the result bundle into the scene when it finishes.

The clip is what ``scene.motion_splats_result.source`` says, never a silent fallback:
``PATH`` reads ``clip_path`` (a dataset folder, a video, an image folder or a clip
manifest); ``MOVIE_CLIP`` exports a clip manifest (``addon.exporters``) of the active
Movie Clip, with the scene camera only when it moves (else the engine solves the
cameras and the artist is told why). Results go to ``<Results>/<clip name>/`` beside the
.blend (:func:`results_root`), never into the extension's folder, which an uninstall
deletes. Nothing here blocks: the job
timer (``addon.jobs``) shows progress and runs the completion callback on the main thread.
"""

from __future__ import annotations

import re
import uuid
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


def results_root(context) -> Path:
    """The folder results go to: the scene's Results setting (relative paths beside the
    .blend), or the preferences' folder while the .blend is unsaved."""
    settings = reconstruct_settings(context)
    out = settings.output_dir if settings is not None else ""
    if not out or (out.startswith("//") and not bpy.data.filepath):
        return preferences.results_dir(context)
    return Path(bpy.path.abspath(out))


def result_paths(context, clip_name: str) -> tuple[Path, Path]:
    """``(bundle_dir, manifest_path)`` of a new result named after the clip: ``<root>/<clip>``
    and ``<root>/<clip>.clip.json`` (``<clip>-2`` ... when taken; nothing is overwritten)."""
    root = results_root(context)
    root.mkdir(parents=True, exist_ok=True)
    stem = bpy.path.clean_name(Path(clip_name).stem or clip_name) or "clip"
    n = 1
    while True:
        name = stem if n == 1 else f"{stem}-{n}"
        bundle, manifest = root / name, root / f"{name}.clip.json"
        if not bundle.exists() and not manifest.exists():
            return bundle, manifest
        n += 1


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


#: Scene custom property naming the reconstructions started from it (see :func:`target_scene`).
TOKEN_KEY = "ms_job_tokens"


def mark_scene(scene) -> str:
    """Tag ``scene`` with a fresh token so the completion callback finds this very scene
    (a scene of the same name in another file is not it)."""
    token = uuid.uuid4().hex
    tokens = str(scene.get(TOKEN_KEY, "")).split()[-7:]
    scene[TOKEN_KEY] = " ".join(tokens + [token])
    return token


def target_scene(token: str):
    """The scene tagged with ``token`` in the open file, or None (closed, reloaded, deleted)."""
    for scene in bpy.data.scenes:
        if token in str(scene.get(TOKEN_KEY, "")).split():
            return scene
    return None


def _on_complete(token: str):
    """Completion callback: build the bundle into the scene it was started from, only if
    that scene is still open (otherwise say where the result is), and only in Object
    Mode (otherwise the build waits for it: see :func:`addon.jobs.defer`)."""

    def done(job):
        if job.state != "finished":
            return
        bundle = (job.result or {}).get("bundle") or job.process.argv[job.process.argv.index("--out") + 1]
        if not jobs.object_mode():
            jobs.defer(job, lambda: build_result(job, token, bundle),
                       "Finished: the result is built when you return to Object Mode")
            return
        build_result(job, token, bundle)

    return done


def build_result(job, token: str, bundle: str) -> None:
    """Build ``bundle`` into the scene tagged ``token``; notes go to the job's log."""
    scene = target_scene(token)
    if scene is None:
        job.callback_error = (f"The result was not built: the scene it was started from is no longer open. "
                              f"Import it with Import Result Bundle from {bundle}")
        return
    result = getattr(scene, props_mod.SCENE_ATTR, None)
    density, preview, with_rig = 1.0, "POINTS", True
    if result is not None:
        density, preview, with_rig = result.density, result.preview, result.with_rig
    from ..addon.build import build_bundle_into_scene

    view_layer = scene.view_layers[0] if bpy.context.scene != scene else bpy.context.view_layer
    with bpy.context.temp_override(scene=scene, view_layer=view_layer):
        res = build_bundle_into_scene(bpy.context, bundle, density=density, preview=preview, with_rig=with_rig)
    if result is not None:
        result.bundle_path = str(bundle)
    job.logs.append(f"[info] Built '{res['collection'].name}'; use Set Up Render to render it from its camera")
    for line in res["scene_changes"]:
        job.logs.append(f"[info] Scene {line}")
    push_undo(f"Motion Splats: build {res['collection'].name}")


def push_undo(message: str) -> None:
    """An undo step for a change made from a timer (no operator pushes one there)."""
    try:
        bpy.ops.ed.undo_push(message=message)
    except RuntimeError:  # no window (background mode): nothing to undo into
        pass


def footage_cameras(context, movieclip, use_scene_camera: bool) -> tuple[list | None, str]:
    """Cameras to send with the Movie Clip, and what to tell the artist about them.

    The scene camera is sent only when it moves over the clip: a factory Camera, or the
    footage camera Import Footage creates, exports identical poses, and training on them
    is training on a guess. Then (and without a camera) the engine solves the cameras
    from the footage.
    """
    from ..addon import exporters, footage

    cam = context.scene.camera
    if not use_scene_camera:
        return None, "Cameras: solved by the engine (Use Scene Camera is off)"
    if cam is None or cam.type != "CAMERA":
        return None, "Cameras: the scene has no camera, so the engine solves them from the footage"
    cams = exporters.clip_cameras(context.scene, movieclip, cam)
    if not footage.cameras_move([c["w2c"] for c in cams]):
        solved = movieclip.tracking.reconstruction.is_valid
        how = ("the clip has a camera solve: press Tracked Camera (Reconstruct panel) to animate a camera "
               "with it" if solved else "to give it real cameras, track and solve the camera in the Movie Clip "
               "Editor, then press Tracked Camera (Reconstruct panel)")
        return None, (f"Camera '{cam.name}' does not move over the clip (never tracked or animated), so it is "
                      f"not sent: the engine solves the cameras from the footage; {how}")
    return cams, f"Cameras: scene camera '{cam.name}' ({len(cams)} frames)"


def _export_footage(op, context, settings):
    """``(clip_path, bundle_dir, camera_note)`` for the chosen source, or None after a report."""
    from ..addon.exporters import write_clip_manifest
    from ..engine.errors import EngineError

    if settings.source == "PATH":
        clip = bpy.path.abspath(settings.clip_path) if settings.clip_path else ""
        if not clip or not Path(clip).exists():
            op.report({"ERROR"}, f"Clip Path not found: {clip or '(empty)'}; choose a dataset folder, video or "
                                 "clip manifest, or set Source to Movie Clip")
            return None
        bundle, _ = result_paths(context, Path(clip).name)
        return clip, bundle, "Cameras: read by the engine from the clip path (solved when it has none)"
    movieclip = active_movieclip(context)
    if movieclip is None:
        op.report({"ERROR"}, "No footage: use Import Footage to load a Movie Clip, or set Source to Clip Path")
        return None
    try:
        cams, note = footage_cameras(context, movieclip, settings.use_scene_camera)
        name = Path(movieclip.name).stem
        if movieclip.source == "SEQUENCE":  # "shot_0001.png" -> "shot"
            name = re.sub(r"[_.\-]*\d+$", "", name) or name
        bundle, manifest = result_paths(context, name)
        write_clip_manifest(manifest, context.scene, movieclip, with_cameras=False, cameras=cams)
    except (EngineError, OSError, ValueError) as exc:
        op.report({"ERROR"}, f"Cannot export the clip manifest: {exc}")
        return None
    return str(manifest), bundle, note


def start_training(op, context, *, resume: bool):
    """Shared body of Reconstruct and Resume; returns the operator's result set."""
    settings = reconstruct_settings(context)
    if settings is None:
        op.report({"ERROR"}, "Motion Splats is not registered in this scene")
        return {"CANCELLED"}
    python = preferences.engine_python_or_report(context, op)
    if not python:
        return {"CANCELLED"}
    note = ""
    if resume:
        bundle = bpy.path.abspath(settings.bundle_path) if settings.bundle_path else ""
        clip = bpy.path.abspath(settings.last_clip) if settings.last_clip else ""
        if not bundle or not Path(bundle).is_dir():
            op.report({"ERROR"}, "Nothing to resume: run Reconstruct first")
            return {"CANCELLED"}
        if not clip or not Path(clip).exists():
            op.report({"ERROR"}, f"The clip of the last run is missing: {clip or '(none)'}")
            return {"CANCELLED"}
        steps = finished_run(bundle)
        if steps is not None:
            op.report({"ERROR"}, finished_message(steps))
            return {"CANCELLED"}
        # the engine resumes only the run it checkpointed: its preset and step count, whatever
        # the panel says now
        preset = settings.last_preset or settings.preset
        steps = settings.last_steps
    else:
        preset, steps = settings.preset, settings.steps
        try:
            found = _export_footage(op, context, settings)
        except OSError as exc:
            op.report({"ERROR"}, f"Cannot create the results folder {results_root(context)}: {exc}; set "
                                 "Results to a writable folder")
            return {"CANCELLED"}
        if found is None:
            return {"CANCELLED"}
        clip, bundle, note = found
        bundle = str(bundle)
    args = train_args(clip, bundle, preset, resume=resume, steps=steps,
                      device=preferences.device(context), models=preferences.onnx_models(context))
    process = EngineProcess.for_engine(python, "train", args, env=preferences.engine_env(context))
    label = "Resume" if resume else "Reconstruct"
    job = jobs.start(JOB_KIND, process, label=label, on_complete=_on_complete(mark_scene(context.scene)))
    if note:
        job.logs.append(f"[info] {note}")
    settings.bundle_path = bundle
    settings.last_clip = clip
    settings.last_preset = preset
    settings.last_steps = steps
    if job.state == "failed":
        op.report({"ERROR"}, " ".join(job.error_summary()))
        return {"CANCELLED"}
    static = "does not move" in note
    op.report({"WARNING"} if static else {"INFO"}, f"{label}: training {Path(clip).name} into {bundle}"
              + (f". {note}" if note else ""))
    return {"FINISHED"}


_FINISHED_CACHE: dict = {}


def finished_run(bundle: str) -> int | None:
    """Steps of the finished run in ``bundle`` (``engine.bundle.finished_steps``), else None.

    Poll calls this on every redraw: the answer is cached by the ``scene.json`` and
    checkpoint file stamps, so only a changed bundle is read again."""
    from ..engine.bundle import SCENE_FILE, finished_steps

    folder = Path(bundle)
    stamps = []
    for f in (folder / SCENE_FILE, folder / "checkpoints" / "checkpoint.pt"):
        try:
            st = f.stat()
            stamps.append((st.st_mtime_ns, st.st_size))
        except OSError:
            stamps.append(None)
    key = (str(folder), tuple(stamps))
    if key not in _FINISHED_CACHE:
        if len(_FINISHED_CACHE) > 32:
            _FINISHED_CACHE.clear()
        _FINISHED_CACHE[key] = finished_steps(folder) if stamps[0] is not None else None
    return _FINISHED_CACHE[key]


def finished_message(steps: int) -> str:
    return (f"The last run is finished ({steps} steps): nothing to resume; Reconstruct trains again "
            "into a new folder")


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
    """Continue the last reconstruction from its checkpoint (after Cancel); a finished run has none"""

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
        steps = finished_run(bpy.path.abspath(settings.bundle_path))
        if steps is not None:
            cls.poll_message_set(finished_message(steps))
            return False
        return True

    def execute(self, context):
        return start_training(self, context, resume=True)


CLASSES = (MOTIONSPLATS_OT_reconstruct, MOTIONSPLATS_OT_resume)
