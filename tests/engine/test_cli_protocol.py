"""The CLI entry point, the JSON-lines protocol and atomic writes."""

import io
import json
import os
import subprocess
import sys

import pytest

from engine import fsutil
from engine.protocol import PROTOCOL_VERSION, Reporter, parse_event

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _engine(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "engine", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def test_help_lists_commands():
    out = _engine("--help")
    assert out.returncode == 0
    assert "selftest" in out.stdout and "version" in out.stdout


def test_every_command_and_bench_formats_its_help():
    """argparse formats a help text only when asked: a stray '%' in one (it takes it for a
    format field) breaks `--help` of that command alone."""
    import argparse

    from engine.bench.__main__ import build_parser as bench_parser
    from engine.cli import build_parser

    for parser in (build_parser(), bench_parser()):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        assert subs and subs[0].choices
        for name, sub in subs[0].choices.items():
            assert sub.format_help(), name


def test_selftest_reports_versions_as_json_lines():
    out = _engine("selftest", "--jsonl")
    assert out.returncode == 0, out.stderr
    events = [parse_event(line) for line in out.stdout.splitlines()]
    assert events and all(events)
    result = events[-1]
    assert result["event"] == "result" and result["ok"] is True
    for name in ("torch", "numpy", "cv2", "onnxruntime", "pycolmap"):
        assert result["versions"][name]


def test_reporter_events_parse_back():
    stream = io.StringIO()
    rep = Reporter(jsonl=True, stream=stream)
    rep.progress("train", 5, 10, loss=0.5, psnr=float("nan"))
    rep.log("hello")
    rep.error("bad", path="/x.json", fix="do y")
    events = [parse_event(line) for line in stream.getvalue().splitlines()]
    assert [e["event"] for e in events] == ["progress", "log", "error"]
    # a stage's first report has no measured rate yet, so no ETA (tests/engine/test_warmup.py)
    assert events[0]["v"] == PROTOCOL_VERSION and events[0]["psnr"] is None and "eta_s" not in events[0]
    assert events[2]["path"] == "/x.json"


@pytest.mark.parametrize("line", ["", "garbage", "{", "[1,2]", '{"v": 1}', '{"v": 2, "event": "log", "message": "x"}',
                                  '{"v": 1, "event": "progress"}', '{"v": 1, "event": "nope"}', "{" * 5000])
def test_parse_event_rejects_garbage(line):
    assert parse_event(line) is None


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "a.json"
    fsutil.atomic_write_json(target, {"a": 1})
    with pytest.raises(ValueError):
        fsutil.atomic_write_json(target, {"a": float("nan")})
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]  # no temp files left behind


def test_sigint_raises_even_when_started_ignored():
    """Cancel sends SIGINT; an engine launched with SIGINT ignored (inherited SIG_IGN from a
    background shell job) must still turn it into KeyboardInterrupt and checkpoint."""
    import signal

    from engine.cli import main

    before = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        assert main(["version"]) == 0
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
