"""`python -m engine.bench build` on a tiny synthetic bundle: valid JSON rows with the
builder's per-part breakdown (behaviour only; timings are not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it

REPO = Path(__file__).resolve().parents[2]
PARTS = ("load_s", "empties_s", "fcurves_s", "rig_s", "attributes_s", "preview_s", "camera_s", "total_s")


def test_synthetic_bundle_is_valid(tmp_path):
    pytest.importorskip("scipy")
    from engine import bundle as B
    from engine.bench.build import synthetic_bundle

    b = B.load_bundle(synthetic_bundle(tmp_path / "b", nodes=12, frames=6, gaussians=300, seed=1))
    assert b.nodes.count == 12 and b.nodes.key_times.shape == (6,) and b.gaussians.count == 300
    assert b.nodes.bind_idx.shape == (300, 4) and np.allclose(b.nodes.bind_w.sum(1), 1, atol=1e-5)
    assert (b.scene["time"]["frame_start"], b.scene["time"]["frame_end"]) == (1, 6)


def test_bench_build_rows(tmp_path):
    pytest.importorskip("bpy")
    r = subprocess.run([sys.executable, "-m", "engine.bench", "build", "--nodes", "15", "--frames", "4",
                        "--gaussians", "400", "--eval-frame", "--work", str(tmp_path), "--json"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = [json.loads(line) for line in r.stdout.splitlines()]  # every stdout line is one JSON row
    assert [row["preview"] for row in rows] == ["POINTS", "ELLIPSOIDS"]
    for row in rows:
        assert (row["nodes"], row["keys"], row["gaussians"]) == (15, 4, 400)
        for key in PARTS + ("eval_frame_s", "wall_s", "peak_rss_mb"):
            assert isinstance(row[key], (int, float)) and row[key] >= 0, key
        parts = sum(row[k] for k in PARTS[:-1])
        assert parts <= row["total_s"] + 1e-3
        assert row["target_s"] == 20.0 and isinstance(row["within_target"], bool)
