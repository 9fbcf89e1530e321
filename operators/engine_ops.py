# SPDX-License-Identifier: GPL-3.0-or-later
"""Operators that talk to the engine process: check, cancel, create its environment,
detect its interpreter. None of them blocks: they start a job (``addon.jobs``) and
return; the job timer reports progress."""

from __future__ import annotations

import bpy
from bpy.props import IntProperty

from ..addon import env_setup, jobs, preferences
from ..addon.bridge import EngineProcess


class MOTIONSPLATS_OT_check_engine(bpy.types.Operator):
    """Run the engine's self-test (python -m engine selftest) in the background and show its versions"""

    bl_idname = "motion_splats.check_engine"
    bl_label = "Check Engine"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if jobs.running("check_engine"):
            cls.poll_message_set("An engine check is already running")
            return False
        return True

    def execute(self, context):
        python = preferences.engine_python_or_report(context, self)
        if not python:
            return {"CANCELLED"}
        process = EngineProcess.for_engine(python, "selftest")
        job = jobs.start("check_engine", process, label="Engine check")
        if job.state == "failed":
            self.report({"ERROR"}, " ".join(job.error_summary()))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Checking the engine with {python}")
        return {"FINISHED"}


class MOTIONSPLATS_OT_cancel_job(bpy.types.Operator):
    """Stop a running engine job (it saves a checkpoint first when it can)"""

    bl_idname = "motion_splats.cancel_job"
    bl_label = "Cancel"
    bl_options = {"REGISTER", "INTERNAL"}

    job_id: IntProperty(name="Job", description="Job to cancel (0: the newest running job)", default=0,
                        options={"SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        if not jobs.running():
            cls.poll_message_set("No engine job is running")
            return False
        return True

    def execute(self, context):
        job = jobs.get(self.job_id) if self.job_id else jobs.latest()
        if job is None or not job.running:
            self.report({"WARNING"}, "That job is not running any more")
            return {"CANCELLED"}
        if job.process.cancel_requested:
            self.report({"INFO"}, f"{job.label}: already stopping")
            return {"CANCELLED"}
        job.cancel()
        self.report({"INFO"}, f"{job.label}: stopping")
        return {"FINISHED"}


class MOTIONSPLATS_OT_create_engine_env(bpy.types.Operator):
    """Create the engine's own Python environment (venv + pip install of torch, OpenCV, ...) in the
    extension's user folder. Downloads about 1 GB; needs online access"""

    bl_idname = "motion_splats.create_engine_env"
    bl_label = "Create Engine Environment"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if jobs.running("env_setup"):
            cls.poll_message_set("The engine environment is being created")
            return False
        return True

    def execute(self, context):
        if not bpy.app.online_access:
            self.report({"ERROR"}, "Online access is disabled: enable Preferences > System > Network > "
                                   "Allow Online Access to download the engine packages, or set an engine "
                                   "interpreter you installed yourself")
            return {"CANCELLED"}
        base = preferences.base_python(context)
        if not base:
            self.report({"ERROR"}, "No Python 3.11/3.12 found on PATH: set Base Python in the add-on preferences")
            return {"CANCELLED"}
        venv_dir = preferences.user_dir("engine-venv")
        venv_dir.parent.mkdir(parents=True, exist_ok=True)
        argv = env_setup.setup_command(base, venv_dir)
        process = EngineProcess(argv, label=f"base Python {base!r}")

        def done(job):
            if job.state == "finished":
                prefs = preferences.get()
                python = (job.result or {}).get("python")
                if prefs is not None and python and not prefs.engine_python:
                    prefs.engine_python = python

        job = jobs.start("env_setup", process, label="Engine environment", on_complete=done)
        if job.state == "failed":
            self.report({"ERROR"}, " ".join(job.error_summary()))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Creating the engine environment in {venv_dir}")
        return {"FINISHED"}


class MOTIONSPLATS_OT_detect_interpreter(bpy.types.Operator):
    """Fill the engine interpreter with the best Python found (the extension's engine environment,
    a development venv, or a Python on PATH). Use Check Engine to verify it"""

    bl_idname = "motion_splats.detect_interpreter"
    bl_label = "Detect Engine Interpreter"
    bl_options = {"REGISTER", "INTERNAL"}

    @classmethod
    def poll(cls, context):
        if preferences.get(context) is None:
            cls.poll_message_set("The add-on preferences are not available")
            return False
        return True

    def execute(self, context):
        candidates = preferences.interpreter_candidates()
        if not candidates:
            self.report({"WARNING"}, "No Python interpreter found; use Create Engine Environment")
            return {"CANCELLED"}
        preferences.get(context).engine_python = candidates[0]
        self.report({"INFO"}, f"Engine interpreter: {candidates[0]}")
        return {"FINISHED"}


CLASSES = (
    MOTIONSPLATS_OT_check_engine,
    MOTIONSPLATS_OT_cancel_job,
    MOTIONSPLATS_OT_create_engine_env,
    MOTIONSPLATS_OT_detect_interpreter,
)
