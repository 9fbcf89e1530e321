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


def test_synthetic_bundle_is_what_it_says(tmp_path):
    """Known answers for the bench's bundle, computed here independently: Catmull-Rom tangents
    (the engine's ``catmull_rom_tangents``), each Gaussian bound to its 4 nearest nodes (brute
    force) with normalised RBF weights ``exp(-d^2 / 2 r^2)``, unit rotation keys, and one period
    of sinusoidal motion (every node moves and its last key equals its first)."""
    pytest.importorskip("scipy")
    import torch

    from engine import bundle as B
    from engine.bench.build import synthetic_bundle
    from engine.geometry.hermite import catmull_rom_tangents

    n = B.load_bundle(synthetic_bundle(tmp_path / "b", nodes=30, frames=7, gaussians=500, seed=2)).nodes
    g = B.load_bundle(tmp_path / "b").gaussians
    kt = torch.as_tensor(n.key_times, dtype=torch.float64)
    for keys, tangents in ((n.pos_keys, n.pos_tangents), (n.rot_keys, n.rot_tangents)):
        want = catmull_rom_tangents(kt, torch.as_tensor(keys, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(tangents, want, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(n.rot_keys, axis=-1), 1.0, atol=1e-6)
    # one period of a sinusoid over the clip: every node moves and ends where it started
    assert (np.linalg.norm(n.pos_keys - n.centers[:, None], axis=-1).max(1) > 1e-3).all()
    np.testing.assert_allclose(n.pos_keys[:, -1], n.pos_keys[:, 0], atol=1e-6)
    np.testing.assert_allclose(n.rot_keys[:, -1], n.rot_keys[:, 0], atol=1e-6)
    d = np.linalg.norm(g.means[:, None] - n.centers[None], axis=-1)  # [G, N]
    nearest = np.sort(np.argsort(d, axis=1, kind="stable")[:, :4], axis=1)
    np.testing.assert_array_equal(np.sort(n.bind_idx, axis=1), nearest)
    dk = np.take_along_axis(d, n.bind_idx, 1)
    w = np.exp(-dk ** 2 / (2 * n.radii[n.bind_idx] ** 2)) + 1e-12
    np.testing.assert_allclose(n.bind_w, w / w.sum(1, keepdims=True), rtol=1e-4, atol=1e-6)


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
        assert row["target_s"] == 20.0 and row["within_target"] is (row["total_s"] <= row["target_s"])
