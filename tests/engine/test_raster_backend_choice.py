"""Backend choice: CUDA without gsplat is announced, never silent (#19); the rasteriser's
modules do not import each other in a cycle."""

from __future__ import annotations

import ast
import io
import json
import logging
from pathlib import Path

import pytest
import torch

import engine.raster.api as api
from engine.cli import forward_warnings
from engine.protocol import Reporter

RASTER = Path(api.__file__).parent


def test_auto_on_cuda_without_gsplat_warns_once(monkeypatch, caplog):
    monkeypatch.setattr(api, "gsplat_available", lambda: False)
    monkeypatch.setattr(api, "_warned_fallback", False)
    with caplog.at_level(logging.WARNING, logger="engine.raster.api"):
        assert api.select_backend("auto", torch.device("cuda")) == "reference"
        assert api.select_backend("auto", torch.device("cuda")) == "reference"
    lines = [r.getMessage() for r in caplog.records if r.name == "engine.raster.api"]
    assert lines == [api.DENSE_FALLBACK_WARNING]
    assert "\n" not in lines[0] and f"gsplat=={api.GSPLAT_TESTED}" in lines[0]


def test_explicit_or_cpu_choice_is_silent(monkeypatch, caplog):
    monkeypatch.setattr(api, "gsplat_available", lambda: False)
    monkeypatch.setattr(api, "_warned_fallback", False)
    with caplog.at_level(logging.WARNING, logger="engine.raster.api"):
        assert api.select_backend("reference", torch.device("cuda")) == "reference"
        assert api.select_backend("auto", torch.device("cpu")) in ("cpu", "reference")
    assert not [r for r in caplog.records if r.name == "engine.raster.api"]


def test_cli_forwards_the_warning_as_one_event(monkeypatch):
    monkeypatch.setattr(api, "gsplat_available", lambda: False)
    monkeypatch.setattr(api, "_warned_fallback", False)
    stream = io.StringIO()
    handler = forward_warnings(Reporter(jsonl=True, stream=stream))
    try:
        api.select_backend("auto", torch.device("cuda"))
    finally:
        logging.getLogger("engine").removeHandler(handler)
    events = [json.loads(line) for line in stream.getvalue().splitlines()]
    assert [(e["event"], e["level"], e["message"]) for e in events] == [("log", "warning", api.DENSE_FALLBACK_WARNING)]


def test_requirements_gpu_pins_the_tested_gsplat():
    lines = (RASTER.parents[1] / "requirements-gpu.txt").read_text().splitlines()
    pins = [ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    assert pins == [f"gsplat=={api.GSPLAT_TESTED}"]


def _local_imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            names.add(node.module or "")
    return names


@pytest.mark.parametrize("backend", ["gsplat_backend", "cpu", "reference"])
def test_backends_do_not_import_the_dispatcher(backend):
    # api imports every backend; a backend importing api back was a cycle (RenderOutput now
    # lives in output.py)
    assert "api" not in _local_imports(RASTER / f"{backend}.py")
    assert "output" in _local_imports(RASTER / "api.py")
