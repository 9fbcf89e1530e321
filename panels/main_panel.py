# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Motion Splats" sidebar panel: the engine job box (stage, progress, metrics, ETA,
Cancel) and the error box of a failed run."""

from __future__ import annotations

import bpy

from ..addon import jobs


def _format_eta(seconds) -> str:
    if seconds is None:
        return ""
    seconds = int(max(seconds, 0))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


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
    col = box.column(align=True)
    if job.stage:
        col.label(text=f"Stage: {job.stage}")
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
    if job.running and job.eta_s is not None:
        col.label(text=f"ETA {_format_eta(job.eta_s)}")
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
