"""`python -m engine.bench train` on a tiny size: valid JSON rows with the documented columns
(behaviour only; timings are never asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it

REPO = Path(__file__).resolve().parents[2]

REQUIRED = ("scene", "width", "height", "gaussians", "nodes", "steps", "its_per_s", "ms_step", "cpu_ms_step",
            "deform", "sh", "raster_fwd", "losses", "backward", "bwd_raster", "bwd_deform", "bwd_torch", "optimizer",
            "densify_stats", "other", "densify_ms", "its_per_s_amortised", "peak_rss_mb", "load_1m", "threads")


def test_bench_train_rows_are_json_with_phases():
    r = subprocess.run([sys.executable, "-m", "engine.bench", "train", "--width", "64", "--gaussians", "1500",
                        "--nodes", "40", "--frames", "12", "--steps", "3", "--warmup", "1", "--repeats", "2",
                        "--json"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = [json.loads(line) for line in r.stdout.splitlines() if line.strip()]
    assert len(rows) == 2
    for row in rows:
        for key in REQUIRED:
            assert key in row, key
        assert row["scene"] == "synthetic" and (row["width"], row["height"]) == (64, 48)
        assert row["steps"] == 3 and row["nodes"] == 40 and 0 < row["gaussians"] <= 1500
        assert row["its_per_s"] > 0 and row["ms_step"] > 0
        # the phases (and "other", the remainder) add up to the step
        parts = sum(row[k] for k in ("deform", "sh", "raster_fwd", "losses", "backward", "optimizer",
                                     "densify_stats", "other"))
        assert abs(parts - row["ms_step"]) < 0.05 * row["ms_step"] + 0.1
        assert row["bwd_raster"] + row["bwd_deform"] + row["bwd_torch"] <= row["backward"] + 0.1



def test_bench_train_figures_are_what_the_trainer_did(monkeypatch):
    """Known answers for the row's figures, measured from outside the bench: the timed window
    runs exactly ``--steps`` training steps (loss evaluations counted here), ``its_per_s`` /
    ``ms_step`` are those steps over that window's wall time (timed here around the trainer's
    ``train()`` call), and ``gaussians`` / ``nodes`` are the trained model's own counts."""
    import time

    from engine.bench import train as bench
    from engine.train.trainer import Trainer

    calls = []  # one per Trainer.train() call: loss evaluations, wall s, model counts before/after
    original_train, original_loss = Trainer.train, Trainer._loss

    def counted_loss(self, f):
        calls[-1]["steps"] += 1
        return original_loss(self, f)

    def timed_train(self):
        calls.append({"steps": 0, "counts": (self.model.num_gaussians, self.model.num_nodes)})
        t0 = time.perf_counter()
        original_train(self)
        calls[-1]["wall"] = time.perf_counter() - t0
        calls[-1]["counts_after"] = (self.model.num_gaussians, self.model.num_nodes)

    monkeypatch.setattr(Trainer, "_loss", counted_loss)
    monkeypatch.setattr(Trainer, "train", timed_train)
    steps, warmup = 6, 2
    row = bench._worker({"clip": None, "width": 64, "gaussians": 1500, "nodes": 40, "frames": 12, "steps": steps,
                         "warmup": warmup, "threads": None, "seed": 0, "device": "cpu"})
    assert [c["steps"] for c in calls] == [warmup, steps], calls  # warm-up, then the timed window
    timed = calls[-1]
    assert row["steps"] == steps
    assert row["its_per_s"] == pytest.approx(steps / timed["wall"], rel=0.05), (row["its_per_s"], timed)
    assert row["ms_step"] == pytest.approx(1000.0 * timed["wall"] / steps, rel=0.05), (row["ms_step"], timed)
    # the timed window neither densifies nor prunes: the counts are the model's all along
    assert (row["gaussians"], row["nodes"]) == timed["counts"] == timed["counts_after"], (row, timed)
    assert row["nodes"] == 40 and 0 < row["gaussians"] <= 1500


def test_paired_summary_compares_rows_pair_by_pair():
    """--baseline's summary row: each tree's median it/s and the per-pair step-time ratios
    (this tree / baseline), an unmatched row left out."""
    from engine.bench.train import paired_summary

    rows = [{"tree": "head", "pair": 1, "its_per_s": 20.0, "ms_step": 50.0},
            {"tree": "baseline", "pair": 1, "its_per_s": 10.0, "ms_step": 100.0},
            {"tree": "baseline", "pair": 2, "its_per_s": 8.0, "ms_step": 125.0},  # a slower minute
            {"tree": "head", "pair": 2, "its_per_s": 10.0, "ms_step": 100.0},
            {"tree": "head", "pair": 3, "its_per_s": 99.0, "ms_step": 1.0}]  # its baseline row missing
    s = paired_summary(rows)
    assert s["summary"] == "paired" and s["pairs"] == 2
    assert s["its_per_s_median"] == 15.0 and s["baseline_its_per_s_median"] == 9.0
    assert (s["step_ratio_min"], s["step_ratio_median"], s["step_ratio_max"]) == (0.5, 0.65, 0.8)
    with pytest.raises(ValueError):
        paired_summary(rows[:1])


def test_bench_train_baseline_must_be_a_tree_of_the_project(tmp_path):
    r = subprocess.run([sys.executable, "-m", "engine.bench", "train", "--baseline", str(tmp_path)], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and str(tmp_path) in r.stderr and "git worktree add" in r.stderr
    assert r.stdout == ""


def test_bench_train_against_a_baseline_tree():
    """Pairs of rows, one per tree, the order alternating, then the summary row (the baseline
    here is this same tree: any tree of the project will do)."""
    r = subprocess.run([sys.executable, "-m", "engine.bench", "train", "--width", "64", "--gaussians", "1500",
                        "--nodes", "40", "--frames", "12", "--steps", "3", "--warmup", "1", "--repeats", "2",
                        "--baseline", str(REPO), "--json"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = [json.loads(line) for line in r.stdout.splitlines() if line.strip()]
    assert [(row.get("tree"), row.get("pair")) for row in rows[:4]] == [
        ("head", 1), ("baseline", 1), ("baseline", 2), ("head", 2)]
    for row in rows[:4]:
        assert row["its_per_s"] > 0 and row["steps"] == 3
    summary = rows[4]
    assert summary["summary"] == "paired" and summary["pairs"] == 2 and len(rows) == 5
    assert summary["step_ratio_min"] <= summary["step_ratio_median"] <= summary["step_ratio_max"]
