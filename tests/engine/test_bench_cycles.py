"""`python -m engine.bench cycles` on tiny sizes: a 3-step training of the bpy `tiny`
synthetic scene, Cycles at 2 samples vs the engine render; valid JSON rows (behaviour only:
a 3-step model is far from the 25 dB goal, so PSNR is only checked to be a number)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it

REPO = Path(__file__).resolve().parents[2]


def test_psnr_files(tmp_path):
    cv2 = pytest.importorskip("cv2")
    from engine.bench.cycles import psnr_files

    a = np.full((12, 16, 3), 100, np.uint8)
    b = a.copy()
    b[0, 0, 0] = 110
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    cv2.imwrite(str(tmp_path / "big.png"), np.full((24, 32, 3), 100, np.uint8))
    expect = 10 * np.log10(255.0 ** 2 / (100.0 / a.size))
    assert abs(psnr_files(tmp_path / "a.png", tmp_path / "b.png") - expect) < 1e-9
    assert psnr_files(tmp_path / "big.png", tmp_path / "a.png") > 100  # resized to the engine's size
    assert psnr_files(tmp_path / "missing.png", tmp_path / "a.png") is None


def test_bench_cycles_rows(tmp_path):
    pytest.importorskip("bpy")
    gen = subprocess.run([sys.executable, "tools/synth_scene.py", "--out", str(tmp_path / "clip"), "--preset", "tiny",
                          "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert gen.returncode == 0, gen.stderr[-2000:]
    r = subprocess.run([sys.executable, "-m", "engine.bench", "cycles", "--clip", str(tmp_path / "clip"), "--steps",
                        "3", "--samples", "2", "--work", str(tmp_path / "work"), "--json"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = [json.loads(line) for line in r.stdout.splitlines()]  # every stdout line is one JSON row
    assert [row["frame"] for row in rows][-1] == "mean" and len(rows) == 4  # first, middle, last + mean
    for row in rows:
        assert isinstance(row["psnr_db"], float)
        assert row["goal_db"] == 25.0 and isinstance(row["meets_goal"], bool)
        assert row["samples"] == 2 and row["train_steps"] == 3 and row["gaussians"] > 0
    mean = rows[-1]
    assert abs(mean["psnr_db"] - np.mean([row["psnr_db"] for row in rows[:-1]])) < 0.011
    frames = [row["frame"] for row in rows[:-1]]
    for f in frames:  # both renders are kept for a look
        assert (tmp_path / "work" / "cycles" / f"frame_{f:05d}.png").is_file()
        assert (tmp_path / "work" / "engine" / f"frame_{f:05d}.png").is_file()
    # the known answer: Cycles path-traces the same bundle the engine rasterises; with Set Up
    # Render's minimum transparent bounces (no Russian roulette through the splats) even 2
    # samples agree closely, and 16 reach the goal (measured on this scene: 25.5 dB at 2
    # samples, 27.9 at 16; 18.1 and 25.7 with Cycles' default of 0)
    assert mean["psnr_db"] > 22.0, mean
    r = subprocess.run([sys.executable, "-m", "engine.bench", "cycles", "--clip", str(tmp_path / "clip"), "--steps",
                        "3", "--samples", "16", "--work", str(tmp_path / "work16"), "--json"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    mean16 = [json.loads(line) for line in r.stdout.splitlines()][-1]
    assert mean16["psnr_db"] > mean["psnr_db"] + 1.0 and mean16["psnr_db"] >= 25.0, (mean["psnr_db"], mean16)
