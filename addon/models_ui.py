# SPDX-License-Identifier: GPL-3.0-or-later
"""The Models box of the add-on preferences: the engine's model registry with Download /
Remove buttons (issue #20).

The list comes from ``engine/models`` (standard library only, imported here directly):
each model's role, size, licence (non-commercial ones flagged) and whether it is in the
per-user model cache, which the engine's ``train`` then uses on its own. *Download* runs
``python -m engine models fetch NAME`` as a background job (resumable, hash-checked,
progress in the box, cancellable); it is refused while Blender's *Allow Online Access* is
off, except for a model that ships inside the add-on (a local copy). *Remove* deletes a
model from the cache (quick, local).
"""

from __future__ import annotations

import bpy
from bpy.props import StringProperty

from . import jobs
from .bridge import EngineProcess

#: Job kind of a model download (one job per model: ``model:<name>``).
JOB_PREFIX = "model:"

OFFLINE_MESSAGE = ("Online access is disabled: enable Preferences > System > Network > Allow Online Access "
                   "to download models (or pass your own ONNX files in the model paths above)")


def _engine_models():
    """The engine's stdlib-only model modules (registry + cache)."""
    from ..engine.models import registry, store

    return registry, store


def online_access() -> bool:
    """Blender's *Allow Online Access* (a function so tests can stand in for the user)."""
    return bool(getattr(bpy.app, "online_access", True))


def download_refusal(spec) -> str | None:
    """Why a download of ``spec`` may not start now (None: it may)."""
    if spec.shipped_path is not None:
        return None  # a local copy from the add-on itself: no network
    if not spec.urls:
        return spec.note or "no download is published for this model: export it to ONNX yourself"
    if not online_access():
        return OFFLINE_MESSAGE
    return None


def _job(name: str):
    return jobs.latest(JOB_PREFIX + name)


class MOTIONSPLATS_OT_model_download(bpy.types.Operator):
    """Download this model into the model cache in the background (resumable, checked against its
    SHA-256); needs Allow Online Access"""

    bl_idname = "motion_splats.model_download"
    bl_label = "Download Model"
    bl_options = {"REGISTER", "INTERNAL"}

    name: StringProperty(name="Model", description="Registry name of the model", options={"SKIP_SAVE"})

    def execute(self, context):
        from . import preferences

        registry, _store = _engine_models()
        try:
            spec = registry.get_spec(self.name)
        except Exception as exc:  # noqa: BLE001 - the engine's InputError, shown as one line
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        job = _job(spec.name)
        if job is not None and job.running:
            self.report({"WARNING"}, f"{spec.name} is already downloading")
            return {"CANCELLED"}
        refusal = download_refusal(spec)
        if refusal:
            self.report({"ERROR"}, refusal)
            return {"CANCELLED"}
        python = preferences.engine_python_or_report(context, self)
        if not python:
            return {"CANCELLED"}
        env = preferences.engine_env(context)
        process = EngineProcess.for_engine(python, "models", ["fetch", spec.name], env=env)
        job = jobs.start(JOB_PREFIX + spec.name, process, label=f"Download {spec.name}")
        if job.state == "failed":
            self.report({"ERROR"}, " ".join(job.error_summary()))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Downloading {spec.name} ({spec.size_text})")
        return {"FINISHED"}


class MOTIONSPLATS_OT_model_remove(bpy.types.Operator):
    """Delete this model (and any unfinished download of it) from the model cache"""

    bl_idname = "motion_splats.model_remove"
    bl_label = "Remove Model"
    bl_options = {"REGISTER", "INTERNAL"}

    name: StringProperty(name="Model", description="Registry name of the model", options={"SKIP_SAVE"})

    def execute(self, context):
        registry, store = _engine_models()
        try:
            spec = registry.get_spec(self.name)
            job = _job(spec.name)
            if job is not None and job.running:
                self.report({"ERROR"}, f"{spec.name} is downloading: cancel the download first")
                return {"CANCELLED"}
            removed = store.ModelStore().remove(spec)
        except Exception as exc:  # noqa: BLE001 - InputError (unknown name, file in use): one line
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Removed {spec.name}" if removed else f"{spec.name} was not installed")
        return {"FINISHED"}


_STATUS_TEXT = {"installed": "installed", "missing": "not installed", "partial": "partly downloaded",
                "changed": "changed since download (verify)", "unrecorded": "unverified file"}


def _draw_job(row, job) -> bool:
    """Progress (with a cancel button) or the failure of a model's last download; True while running."""
    if job is None:
        return False
    if job.running:
        done = f"{job.step / 1e6:.1f}" if job.step else "0"
        total = f" / {job.total / 1e6:.1f} MB" if job.total else " MB"
        row.label(text=f"{done}{total} ({100 * job.factor:.0f} %)", icon="TIME")
        op = row.operator("motion_splats.cancel_job", text="", icon="X")
        op.job_id = job.id
        return True
    if job.state == "failed":
        row.label(text=" ".join(job.error_summary())[:160] or "download failed", icon="ERROR")
    return False


def draw(layout, context) -> None:
    """Draw the Models box (one row per registry model) into ``layout``."""
    try:
        registry, store = _engine_models()
        specs, cache = registry.load_registry(), store.ModelStore()
    except Exception as exc:  # noqa: BLE001 - a broken registry must not break the preferences
        layout.label(text=f"Models: {exc}"[:160], icon="ERROR")
        return
    box = layout.box()
    box.label(text="Models (optional; better priors, used automatically once installed)")
    box.label(text=f"Cache: {cache.root}", icon="FILE_FOLDER")
    if not online_access():
        box.label(text="Online access is off: downloads are disabled (Preferences > System > Network)",
                  icon="ERROR")
    for spec in specs:
        col = box.column(align=True)
        state = cache.state(spec)
        row = col.row(align=True)
        icon = "CHECKMARK" if state.status == "installed" else "BLANK1"
        row.label(text=f"{spec.name}  ({spec.role}, {spec.size_text})", icon=icon)
        row.label(text=_STATUS_TEXT.get(state.status, state.status))
        running = _draw_job(row, _job(spec.name))
        if not running:
            if state.status != "installed" and spec.fetchable:
                sub = row.row(align=True)
                sub.enabled = download_refusal(spec) is None
                op = sub.operator("motion_splats.model_download", text="Download", icon="IMPORT")
                op.name = spec.name
            if state.status != "missing":
                op = row.operator("motion_splats.model_remove", text="", icon="TRASH")
                op.name = spec.name
        lic = col.row()
        lic.label(text=f"Licence: {spec.license}"[:160], icon="ERROR" if spec.non_commercial else "BLANK1")
        if spec.non_commercial:
            col.label(text="NON-COMMERCIAL: not for paid work", icon="BLANK1")
        elif not spec.fetchable:
            col.label(text=(spec.note or "bring your own ONNX export")[:160], icon="BLANK1")


CLASSES = (MOTIONSPLATS_OT_model_download, MOTIONSPLATS_OT_model_remove)
