"""Issue #22 (add-on): the job pump never freezes Blender and never loses an event, and a
silent engine is reported (and stopped after a long limit).

* A flood of events is applied over several timer ticks, each within a small time budget,
  in order, and the final ``result``/``error`` event is applied before the job completes,
  even when the process ended (``state`` final) while the whole flood was still queued.
* The no-output watchdog: a fake engine prints one event and then sleeps; its job box says
  the engine has been silent (Cancel still works), and with a stop limit it ends 'failed'
  with a message naming the preference. An engine that keeps talking is never flagged.
"""

from __future__ import annotations

import time

import pytest

from tests.addon._support import bpy, clean_jobs, fake_engine, registered, user_dir, wait_until  # noqa: F401
from tests.addon.test_panels_draw import Layout, labels

pytestmark = pytest.mark.timeout(180)

N_FLOOD = 100_000


def _flood(tmp_path, last: str) -> list[str]:
    """A fake engine that writes ``N_FLOOD`` progress events in one burst, then ``last``."""
    return fake_engine(tmp_path, "flood", f"""
        out = []
        for i in range({N_FLOOD}):
            out.append(json.dumps({{"v": 1, "event": "progress", "time": 0.0, "stage": "train",
                                    "step": i, "total": {N_FLOOD}}}))
        sys.stdout.write("\\n".join(out) + "\\n")
        sys.stdout.flush()
        if {last!r} == "result":
            emit("result", bundle="/tmp/flood")
        else:
            emit("error", message="the flood ended badly", fix="nothing")
            sys.exit(2)
    """)


def _start_after_exit(jobs, bridge, argv, tmp_path, seen, done, monkeypatch):
    """Start the flood and wait for its process to end *before* any drain: the state is
    final while every event is still queued (the case a naive cap would lose)."""
    orig = jobs.Job.apply
    monkeypatch.setattr(jobs.Job, "apply",
                        lambda job, event: (seen.append(event.get("step", event["event"])), orig(job, event)))
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    proc.wait(60)  # bridge.wait never polls: all events are still in the queue
    assert proc.done and proc.pending_events == N_FLOOD + 1
    return jobs.start("train", proc, label="Flood", on_complete=done.append)  # its first tick


def test_flood_is_applied_over_several_ticks_and_the_result_last(extension, registered, tmp_path, clean_jobs,
                                                                  monkeypatch):
    jobs, bridge = clean_jobs, extension.addon.bridge
    seen, done, ticks = [], [], []
    job = _start_after_exit(jobs, bridge, _flood(tmp_path, "result"), tmp_path, seen, done, monkeypatch)
    while not job.completed:
        t0 = time.perf_counter()
        again = jobs._timer()  # one timer tick
        ticks.append(time.perf_counter() - t0)
        if not job.completed:
            # the timer comes back soon while events are queued, and the job is still running
            assert again == jobs.BACKLOG_INTERVAL_S and job.running and jobs.backlog() > 0
            assert not done and job.result is None
        assert len(ticks) < 10_000
    # one tick applied everything before (~0.5 s for 100k events); now each tick is bounded
    assert len(ticks) >= 5, len(ticks)
    ticks.sort()
    median = ticks[len(ticks) // 2]
    assert median < 0.06 and ticks[-1] < 0.3, f"median {median:.3f} s, max {ticks[-1]:.3f} s"
    # nothing lost, in order, and the result was applied before the completion callback
    assert seen == list(range(N_FLOOD)) + ["result"]
    assert done == [job] and job.state == "finished" and job.result["bundle"] == "/tmp/flood"
    assert job.step == N_FLOOD - 1 and jobs.backlog() == 0
    assert jobs._timer() is None  # nothing left: the timer stops


def test_error_after_a_flood_is_not_lost(extension, registered, tmp_path, clean_jobs, monkeypatch):
    jobs, bridge = clean_jobs, extension.addon.bridge
    seen, done = [], []
    job = _start_after_exit(jobs, bridge, _flood(tmp_path, "error"), tmp_path, seen, done, monkeypatch)
    jobs.wait(job, timeout=60)
    assert seen[-1] == "error" and len(seen) == N_FLOOD + 1
    assert done == [job] and job.state == "failed"
    assert job.error["message"] == "the flood ended badly"
    assert job.error_summary()[0] == "the flood ended badly"


def test_poll_events_cap_keeps_the_rest(extension, tmp_path):
    bridge = extension.addon.bridge
    argv = fake_engine(tmp_path, "ten", """
        for i in range(10):
            emit("progress", stage="s", step=i, total=10)
        emit("result", bundle="b")
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    proc.wait(20)
    assert proc.state == "finished" and proc.pending_events == 11
    got = proc.poll_events(4)
    assert [e["step"] for e in got] == [0, 1, 2, 3] and proc.pending_events == 7
    rest = proc.poll_events(100)
    assert [e.get("step") for e in rest] == [4, 5, 6, 7, 8, 9, None] and rest[-1]["event"] == "result"
    assert proc.poll_events() == [] and proc.pending_events == 0


_HUNG = """
    emit("progress", stage="train", step=1, total=10)
    time.sleep(120)  # hung: no output at all from here on
"""


def _pump(jobs, predicate, timeout):
    return wait_until(lambda: (jobs.drain(), predicate())[1], timeout, step=0.05)


def _box(extension, job) -> list[str]:
    log: list = []
    extension.panels.main_panel.draw_job(Layout(log), job)
    return labels(log)


def test_silent_engine_is_reported_and_cancel_works(extension, registered, tmp_path, clean_jobs):
    jobs, bridge = clean_jobs, extension.addon.bridge
    registered.silence_warn_s, registered.silence_stop_s = 1, 0
    job = jobs.start("train", bridge.EngineProcess(fake_engine(tmp_path, "hung", _HUNG), cwd=tmp_path),
                     label="Reconstruct")
    assert _pump(jobs, lambda: job.step == 1, 15)
    assert not job.silence_lines()  # it just spoke
    assert _pump(jobs, lambda: bool(job.silence_lines()), 10)
    text = _box(extension, job)
    assert any(t.startswith("The engine has printed nothing for 1 s") or
               t.startswith("The engine has printed nothing for 2 s") for t in text), text
    assert any("Cancel stops it" in t for t in text) and not any("It is stopped after" in t for t in text)
    assert "Reconstruct: running" in text and job.running
    assert any("printed nothing" in line for line in job.logs)
    # no stop limit: it keeps running (a first run may compile for minutes)
    assert not _pump(jobs, lambda: job.completed, 1.5) and job.running
    assert bpy.ops.motion_splats.cancel_job(job_id=job.id) == {"FINISHED"}
    assert not job.silence_lines()  # "Stopping ..." instead
    jobs.wait(job, timeout=15)
    assert job.state == "cancelled" and job.error_summary() == ["Cancelled."]


def test_silent_engine_is_stopped_after_the_limit(extension, registered, tmp_path, clean_jobs):
    jobs, bridge = clean_jobs, extension.addon.bridge
    registered.silence_warn_s, registered.silence_stop_s = 1, 2
    job = jobs.start("train", bridge.EngineProcess(fake_engine(tmp_path, "hung", _HUNG), cwd=tmp_path),
                     label="Reconstruct")
    assert _pump(jobs, lambda: bool(job.silence_lines()), 15)
    assert any("It is stopped after 2 s of silence (Preferences)" in t for t in _box(extension, job))
    assert _pump(jobs, lambda: job.completed, 20)
    assert job.state == "failed"
    summary = job.error_summary()
    assert summary[0].startswith("The engine printed nothing for 2 s and was stopped as hung"), summary
    assert "Stop Silent Engine After" in summary[0]
    assert job.process.exit_code is not None  # the process is gone, not orphaned


def test_talking_engine_is_never_flagged(extension, registered, tmp_path, clean_jobs):
    jobs, bridge = clean_jobs, extension.addon.bridge
    registered.silence_warn_s, registered.silence_stop_s = 1, 2
    argv = fake_engine(tmp_path, "chatty", """
        for i in range(12):
            emit("progress", stage="train", step=i, total=12)
            time.sleep(0.3)
        emit("result", bundle="b")
    """)
    job = jobs.start("train", bridge.EngineProcess(argv, cwd=tmp_path))
    flagged = []
    assert _pump(jobs, lambda: (flagged.append(bool(job.silence_lines())), job.completed)[1], 30)
    assert job.state == "finished" and not any(flagged)


def test_silence_preferences_are_drawn(extension, registered):
    from tests.addon.test_panels_draw import draw

    log = draw(type(registered), owner=registered)
    props = [c[1][1] for c in log if c[0] == "prop"]
    assert "silence_warn_s" in props and "silence_stop_s" in props
    assert (registered.silence_warn_s, registered.silence_stop_s) == (120, 3600)
