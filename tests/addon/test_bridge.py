"""EngineProcess with fake engines (tiny scripts) and once with the real engine."""

from __future__ import annotations

import os
import signal
import sys
import time

import pytest

from tests.addon._support import VENV_PYTHON, fake_engine, wait_until

pytestmark = pytest.mark.timeout(120)


@pytest.fixture()
def bridge(extension):
    return extension.addon.bridge


def _collect(proc, timeout=20.0):
    events = []
    deadline = time.monotonic() + timeout
    while not proc.done:
        events += proc.poll_events()
        assert time.monotonic() < deadline, "engine did not finish"
        time.sleep(0.02)
    events += proc.poll_events()
    return events


def test_engine_command_and_cwd(bridge):
    argv = bridge.engine_command("/x/python", "train", ["--clip", "a b"])
    assert argv == ["/x/python", "-m", "engine", "train", "--jsonl", "--clip", "a b"]
    assert (bridge.EXTENSION_ROOT / "engine" / "protocol.py").is_file()
    proc = bridge.EngineProcess.for_engine("/x/python", "selftest")
    assert proc.cwd == str(bridge.EXTENSION_ROOT) and proc.state == "idle"
    assert "PYTHONHOME" not in proc.env and proc.env["PYTHONUNBUFFERED"] == "1"


def test_progress_then_result_in_order(bridge, tmp_path):
    argv = fake_engine(tmp_path, "ok", """
        for i in range(1, 4):
            emit("progress", stage="train", step=i, total=3, loss=1.0 / i, psnr=20 + i, eta_s=3 - i)
        emit("log", level="info", message="writing bundle")
        emit("result", bundle="/tmp/b")
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    events = _collect(proc)
    assert [e["event"] for e in events] == ["progress"] * 3 + ["log", "result"]
    assert [e["step"] for e in events[:3]] == [1, 2, 3]
    assert proc.state == "finished" and proc.exit_code == 0
    assert proc.result["bundle"] == "/tmp/b" and proc.error_summary() == []
    assert proc.last_progress["psnr"] == 23


def test_garbage_and_huge_lines_are_ignored(bridge, tmp_path):
    argv = fake_engine(tmp_path, "garbage", """
        print("hello from a stray print")
        print("{not json")
        print('{"event": "progress", "stage": "x", "step": 1}')  # no version
        print('{"v": 1, "event": "progress"}')  # missing fields
        print('[1, 2, 3]')
        emit("progress", stage="prep", step=1, total=2)
        sys.stdout.write("x" * (3 * 1024 * 1024) + "\\n")
        sys.stdout.write('{"v": 1, "event": "result", "pad": "' + "y" * (2 * 1024 * 1024) + '"}\\n')
        sys.stdout.buffer.write(b"\\xff\\xfe binary junk\\n"); sys.stdout.flush()
        emit("progress", stage="prep", step=2, total=2)
        emit("result", bundle="ok")
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    events = _collect(proc)
    assert [(e["event"], e.get("step")) for e in events] == [("progress", 1), ("progress", 2), ("result", None)]
    assert events[-1]["bundle"] == "ok"
    assert proc.state == "finished"
    assert any("stray print" in t for t in proc.text_lines)
    assert all(len(t) < 5000 for t in proc.text_lines)


def test_crash_gives_clean_summary(bridge, tmp_path):
    argv = fake_engine(tmp_path, "crash", """
        emit("progress", stage="load", step=1, total=10)
        def inner():
            raise RuntimeError("the GPU caught fire")
        inner()
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    events = _collect(proc)
    assert [e["event"] for e in events] == ["progress"]
    assert proc.state == "failed" and proc.exit_code == 1
    summary = proc.error_summary()
    text = "\n".join(summary)
    assert "RuntimeError: the GPU caught fire" in text
    assert "Traceback" not in text and 'File "' not in text and "inner()" not in text
    assert "exit code 1" in summary[0]


def test_engine_error_event_wins(bridge, tmp_path):
    argv = fake_engine(tmp_path, "err", """
        emit("error", message="clip has no frames", path="/clips/a", fix="choose another folder")
        sys.stderr.write("some noise\\n")
        sys.exit(2)
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    _collect(proc)
    assert proc.state == "failed" and proc.exit_code == 2
    assert proc.error_summary() == ["clip has no frames", "File: /clips/a", "Fix: choose another folder"]


def test_exit_zero_without_result_fails(bridge, tmp_path):
    argv = fake_engine(tmp_path, "noresult", """
        emit("progress", stage="x", step=1, total=1)
        print("done, but no result")
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    _collect(proc)
    assert proc.state == "failed" and proc.exit_code == 0
    assert "without a result" in proc.error_summary()[0]


def test_bad_interpreter_names_it_and_points_to_preferences(bridge, tmp_path):
    missing = str(tmp_path / "no" / "python3")
    proc = bridge.EngineProcess.for_engine(missing, "selftest").start()
    assert proc.state == "failed" and proc.exit_code is None
    msg = " ".join(proc.error_summary())
    assert missing in msg and "Preferences" in msg and "not found" in msg
    assert proc.poll_events() == []
    not_exec = tmp_path / "python-not-exec"
    not_exec.write_text("")
    proc = bridge.EngineProcess.for_engine(str(not_exec), "selftest").start()
    assert proc.state == "failed"
    assert str(not_exec) in proc.error_summary()[0]


def test_cancel_sleeping_engine(bridge, tmp_path):
    argv = fake_engine(tmp_path, "sleeper", """
        try:
            emit("progress", stage="train", step=1, total=1000)
            while True:
                time.sleep(0.05)
        except KeyboardInterrupt:
            emit("error", message="interrupted; state saved", fix="re-run with --resume")
            sys.exit(130)
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    assert wait_until(lambda: proc.last_progress is not None, 15)
    t0 = time.monotonic()
    proc.cancel(timeout=5)
    assert time.monotonic() - t0 < 0.5  # never blocks the caller
    assert proc.wait(8) == "cancelled"
    assert time.monotonic() - t0 < 5
    assert proc.exit_code == 130 and proc.error_event["message"].startswith("interrupted")
    assert proc.error_summary() == ["Cancelled."]


@pytest.mark.skipif(os.name == "nt", reason="POSIX signals")
def test_cancel_escalates_to_kill(bridge, tmp_path):
    argv = fake_engine(tmp_path, "stubborn", """
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        emit("progress", stage="train", step=1, total=10)
        while True:
            time.sleep(0.05)
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    assert wait_until(lambda: proc.last_progress is not None, 15)
    t0 = time.monotonic()
    proc.cancel(timeout=0.6)
    assert proc.wait(10) == "cancelled"
    assert proc.exit_code == -signal.SIGKILL
    assert time.monotonic() - t0 < 6


@pytest.mark.skipif(os.name == "nt", reason="POSIX signals")
def test_killed_engine_fails_with_message(bridge, tmp_path):
    argv = fake_engine(tmp_path, "victim", """
        emit("progress", stage="train", step=1, total=10)
        while True:
            time.sleep(0.05)
    """)
    proc = bridge.EngineProcess(argv, cwd=tmp_path).start()
    assert wait_until(lambda: proc.last_progress is not None, 15)
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(10) == "failed"
    assert "SIGKILL" in proc.error_summary()[0]


def test_strip_tracebacks(bridge):
    lines = [
        "warning: something",
        "Traceback (most recent call last):",
        '  File "a.py", line 1, in <module>',
        "    x()",
        "    ^^^",
        "ValueError: bad",
        "",
        "During handling of the above exception, another exception occurred:",
        "",
        "Traceback (most recent call last):",
        '  File "b.py", line 2, in f',
        "KeyError: 'k'",
    ]
    assert bridge.strip_tracebacks(lines) == ["warning: something", "ValueError: bad", "KeyError: 'k'"]


@pytest.mark.skipif(not VENV_PYTHON.is_file(), reason="no engine venv")
def test_real_engine_selftest(bridge):
    proc = bridge.EngineProcess.for_engine(str(VENV_PYTHON), "selftest").start()
    events = _collect(proc, timeout=100)
    assert proc.state == "finished", proc.error_summary()
    result = events[-1]
    assert result["event"] == "result" and result["ok"] is True
    assert result["versions"]["numpy"] and result["versions"]["torch"]
    assert result["python"] == "%d.%d.%d" % sys.version_info[:3] or result["python"]
