"""``python -m engine.bench nodes``: rows have the documented keys and finite values.

The generated-scene test needs bpy (tiny preset, a few seconds to generate + prepare);
the procedural test runs everywhere. No timing asserts.
"""

from __future__ import annotations

import argparse
import math

import pytest

from engine.bench import nodes as bench

GT_KEYS = ("scene", "init", "trajectory", "nodes", "dyn_frac", "dyn_share_gt", "density_ratio", "traj_err",
           "traj_err_dyn", "traj_err_abs", "traj_err_dyn_abs", "zero_motion_dyn", "extent", "wall_s")


def _args(**kw):
    parser = argparse.ArgumentParser()
    parser.add_argument("--json", action="store_true")
    bench.add_arguments(parser)
    args = parser.parse_args([])
    for k, v in kw.items():
        setattr(args, k, v)
    return args


def _check(rows, keys, budget):
    assert [(r["init"], r["trajectory"]) for r in rows] == list(bench.VARIANTS)
    for r in rows:
        for k in keys:
            assert k in r, (k, r)
            if isinstance(r[k], float):
                assert math.isfinite(r[k]), (k, r)
        assert r["nodes"] == budget
        assert 0.0 <= r["dyn_frac"] <= 1.0 and r["density_ratio"] >= 0.0
    # static trajectories and spline trajectories share the MANI centres
    assert rows[0]["dyn_frac"] == rows[1]["dyn_frac"]


def test_generated_scene_rows(tmp_path):
    pytest.importorskip("bpy")
    pytest.importorskip("cv2")
    rows = bench.run(_args(preset="tiny", keep=str(tmp_path / "tiny"), budget=60, skip_speed=True))
    _check(rows, GT_KEYS, 60)
    assert 0.0 < rows[0]["dyn_share_gt"] < 1.0 and rows[0]["extent"] > 0


def test_procedural_rows():
    rows = bench.run(_args(procedural=True, frames=8, budget=60, skip_speed=True))
    _check(rows, ("scene", "init", "trajectory", "nodes", "dyn_frac", "density_ratio", "traj_err", "wall_s"), 60)
