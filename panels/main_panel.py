# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Motion Splats" sidebar panel: the engine job box (stage, progress, metrics, ETA,
Cancel) and the error box of a failed run."""

from __future__ import annotations

import math
import time

import bpy

from ..addon import jobs


def _format_eta(seconds) -> str:
    if seconds is None:
        return ""
    seconds = int(max(seconds, 0))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


#: Log lines shown under a running job.
LOG_LINES = 3
#: Seconds of silence after a finished stage before the panel says the next one is being prepared.
QUIET_S = 3.0
#: What the box calls the engine's stages where their protocol name says little to an artist.
STAGE_NAMES = {"compile": "compiling the engine's kernels", "detail": "shot detail"}
#: A line under the progress bar for these stages (while they run).
STAGE_HINTS = {"compile": "A first run compiles them (about a minute); later runs load them from the cache",
               "detail": "Each frame's own detail of the moving things, seen from the shot's camera"}


def stage_text(job) -> str:
    """``"Stage: <name>"`` for the job box (:data:`STAGE_NAMES` where one is given)."""
    return f"Stage: {STAGE_NAMES.get(job.stage, job.stage)}"


def progress_lines(job, now: float) -> list[str]:
    """Elapsed time, the stage's hint (:data:`STAGE_HINTS`) and the engine's ETA, counted
    down since it arrived (the engine measures it from the stage's rate; a stage without a
    measured rate has none, and none is invented). A silence after a finished stage says
    the next one is being prepared instead of a frozen "ETA 0:00"."""
    lines = [f"Elapsed {_format_eta(now - job.started)}"]
    stage_done = bool(job.total) and job.step >= job.total
    if stage_done and now - job.last_event > QUIET_S:
        lines.append(f"Preparing the next stage (no progress for {int(now - job.last_event)} s)")
        return lines
    if not stage_done and job.stage in STAGE_HINTS:
        lines.append(STAGE_HINTS[job.stage])
    if job.eta_s is not None and not stage_done:
        left = math.ceil(job.eta_s - max(now - job.progress_at, 0.0))
        if left > 0:
            lines.append(f"ETA {_format_eta(left)}")
    return lines


def draw_job(layout, job) -> None:
    """Draw one job's box (used by the panel; reusable by later panels)."""
    box = layout.box()
    header = box.row()
    icons = {"running": "TIME", "finished": "CHECKMARK", "cancelled": "CANCEL", "failed": "ERROR"}
    header.label(text=f"{job.label}: {job.state}", icon=icons.get(job.state, "INFO"))
    if job.running:
        op = header.operator("motion_splats.cancel_job", text="Cancel", icon="X")
        op.job_id = job.id
        if job.process.cancel_requested:
            box.label(text="Stopping (saving a checkpoint)...", icon="SORTTIME")
        silence = job.silence_lines()
        if silence:
            warn = box.column(align=True)
            warn.alert = True
            for i, line in enumerate(silence):
                warn.label(text=line, icon="ERROR" if i == 0 else "BLANK1")
    col = box.column(align=True)
    if job.stage:
        col.label(text=stage_text(job))
    steps = f"{job.step}/{job.total}" if job.total else (str(job.step) if job.stage else "")
    if job.running and hasattr(col, "progress"):
        col.progress(factor=job.factor, type="BAR", text=steps or "starting...")
    elif steps:
        col.label(text=f"Step {steps}")
    metrics = []
    if job.loss is not None:
        metrics.append(f"loss {job.loss:.4g}")
    if job.psnr is not None:
        metrics.append(f"PSNR {job.psnr:.2f} dB")
    if metrics:
        col.label(text="  ".join(metrics))
    if job.running:
        for line in progress_lines(job, time.monotonic()):
            col.label(text=line)
        logs = list(job.logs)[-LOG_LINES:]
        if logs:
            box.separator()
            sub = box.column(align=True)
            for line in logs:
                sub.label(text=line[:160])
    if job.state == "failed":
        err = layout.box()
        err.alert = True
        err.label(text="The engine failed", icon="ERROR")
        for line in job.error_summary():
            err.label(text=line[:200])


class _MainPanel:
    """The job box and Check Engine (drawn in the 3D Viewport and the Movie Clip editor)."""

    bl_label = "Motion Splats"
    bl_region_type = "UI"
    bl_category = "Motion Splats"
    bl_order = 0

    def draw(self, context):
        layout = self.layout
        job = jobs.latest()
        if job is None:
            layout.label(text="No engine job", icon="INFO")
        else:
            draw_job(layout, job)
        row = layout.row(align=True)
        row.operator("motion_splats.check_engine", icon="CHECKMARK")


class MOTIONSPLATS_PT_main(_MainPanel, bpy.types.Panel):
    bl_idname = "MOTIONSPLATS_PT_main"
    bl_space_type = "VIEW_3D"


class MOTIONSPLATS_PT_clip_main(_MainPanel, bpy.types.Panel):
    bl_idname = "MOTIONSPLATS_PT_clip_main"
    bl_space_type = "CLIP_EDITOR"


CLASSES = (MOTIONSPLATS_PT_main, MOTIONSPLATS_PT_clip_main)
