# SPDX-License-Identifier: GPL-3.0-or-later
"""Fine-tune appearance with the trajectories locked.

After editing node F-curves, the artist presses *Fine-tune Appearance*: the edits are
sent to the bundle (``nodes.npz``, as *Send Edits* does), then ``python -m engine
finetune BUNDLE --steps N`` runs in the background (progress and Cancel in the main
panel's job box). The engine trains only the Gaussians' colours, opacities, scales and
rotations under the edited motion, backs up the files it replaces into
``<bundle>/backups/`` and updates the bundle. When it finishes, the Gaussian preview is
rebuilt from the bundle; the node Empties and their F-curves are kept as they are.
"""

from __future__ import annotations

import uuid
from pathlib import Path

import bpy
from bpy.props import BoolProperty, IntProperty

from ..addon import build, exporters, jobs, preferences
from ..addon import properties as props_mod
from ..addon.bridge import EngineProcess
from ..engine import bundle as bundle_io

JOB_KIND = "finetune"
#: Collection custom property naming the fine-tune that will refresh it.
TOKEN_KEY = "ms_finetune_token"
#: jobs that write the same bundle: one at a time
BUSY_KINDS = ("train", JOB_KIND)


def finetune_args(bundle: str, steps: int, device: str = "auto") -> list[str]:
    """Arguments after ``python -m engine finetune --jsonl`` (pure; unit-tested)."""
    args = [str(bundle), "--steps", str(max(1, int(steps)))]
    if device and device != "auto":
        args += ["--device", device]
    return args


def _on_complete(token: str):
    """Rebuild the Gaussian preview of the collection tagged ``token`` from the fine-tuned
    bundle (Empties kept); nothing when that collection is gone (deleted, another file)."""

    def done(job):
        if job.state != "finished":
            return
        if not jobs.object_mode():
            jobs.defer(job, lambda: refresh(job), "Finished: the preview refreshes when you return to Object Mode")
            return
        refresh(job)

    def refresh(job):
        col = next((c for c in bpy.data.collections if c.get(TOKEN_KEY) == token), None)
        if col is None or "ms_bundle" not in col:
            return  # the result was deleted meanwhile (or another file loaded): nothing to refresh
        with_rig = any("ms_rig" in o for o in col.objects)  # rebuild what was built
        build.rebuild_preview(bpy.context, col, density=float(col.get("ms_density", 1.0)), with_rig=with_rig,
                              preview=str(col.get("ms_preview", "POINTS")))

    return done


class MOTIONSPLATS_OT_finetune(bpy.types.Operator):
    """Send the node edits to the bundle and fine-tune the Gaussians' appearance (colour, opacity, scale,
    rotation) in the background with the edited motion locked; the preview refreshes when it finishes"""

    bl_idname = "motion_splats.finetune"
    bl_label = "Fine-tune Appearance"
    bl_options = {"REGISTER"}

    steps: IntProperty(name="Steps", default=0, min=0, description="Optimisation steps (0: the panel's setting)",
                       options={"SKIP_SAVE"})
    send_edits: BoolProperty(name="Send Edits First", default=True,
                             description="Write the node Empties' F-curves into the bundle before fine-tuning")

    @classmethod
    def poll(cls, context):
        if build.bundle_collection(context) is None:
            cls.poll_message_set(build.why_no_result(context))
            return False
        if any(jobs.running(kind) for kind in BUSY_KINDS):
            cls.poll_message_set("An engine job is writing results: wait for it or cancel it")
            return False
        return True

    def execute(self, context):
        col = build.bundle_collection(context)
        bundle = Path(col["ms_bundle"])
        if not (bundle / bundle_io.GAUSSIANS_FILE).is_file():
            self.report({"ERROR"}, f"The bundle has no trained Gaussians yet: {bundle}")
            return {"CANCELLED"}
        python = preferences.engine_python_or_report(context, self)
        if not python:
            return {"CANCELLED"}
        if self.send_edits:
            try:
                sent = exporters.send_edits(col)
            except Exception as exc:  # user-facing: never a traceback in the UI
                self.report({"ERROR"}, f"Cannot send the node edits: {exc}")
                return {"CANCELLED"}
            from .result_ops import report_sent

            report_sent(self, sent)
        s = props_mod.settings(context)
        steps = self.steps or (s.finetune_steps if s is not None else 200)
        process = EngineProcess.for_engine(python, "finetune",
                                           finetune_args(str(bundle), steps, preferences.device(context)),
                                           env=preferences.engine_env(context))
        token = uuid.uuid4().hex
        col[TOKEN_KEY] = token  # a collection of the same name in another file is not this one
        job = jobs.start(JOB_KIND, process, label="Fine-tune", on_complete=_on_complete(token))
        if job.state == "failed":
            self.report({"ERROR"}, " ".join(job.error_summary()))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Fine-tuning the appearance of {bundle.name} ({steps} steps, motion locked)")
        return {"FINISHED"}


CLASSES = (MOTIONSPLATS_OT_finetune,)
