"""``python -m engine.bench solve``: fresh-process repeats of the camera solve agree (issue #21)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_solve_selection import fixed_w2c, render_clip  # noqa: E402

from engine.bench.__main__ import main  # noqa: E402

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it


def test_bench_solve_repeats_in_fresh_processes_agree(tmp_path, capsys):
    folder = tmp_path / "fixed"
    render_clip(folder, fixed_w2c(16))
    assert main(["solve", "--json", "--repeats", "2", "--clips", str(folder)]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(rows) == 1
    row = rows[0]
    assert row["repeats"] == 2 and row["distinct"] == 1, row
    assert row["models"] in ("rotation", "static") and row["path_length"] == 0.0
    assert row["registered"] == "16/16" and row["parallax_px"] < 0.1
