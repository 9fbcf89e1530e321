"""``python -m engine.bench solve``: fresh-process repeats of the camera solve agree (issue #21)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_solve_selection import fixed_w2c, handheld_w2c, render_clip  # noqa: E402

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


def _angle_deg(R):
    """Rotation angles in degrees of ``R [..., 3, 3]``."""
    import numpy as np

    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def test_bench_solve_recovers_known_cameras_and_reports_their_figures(tmp_path, capsys, monkeypatch):
    """Known answer: a handheld camera walking sideways (cameras known, the clip has none). The
    solve the bench times (one child's work, ``--in-process``) recovers every camera's rotation
    relative to the first within 0.5 degrees (gauge-free), and the row's figures are that solve's:
    its camera fingerprint, its registered count and its path length, recomputed here from the
    solved cameras (centres -R^T t)."""
    import hashlib

    import numpy as np

    from engine import pipeline

    w2c = handheld_w2c(16)
    folder = tmp_path / "handheld"
    render_clip(folder, w2c, panel=0.3)
    solved = []
    original = pipeline.open_clip
    monkeypatch.setattr(pipeline, "open_clip", lambda *a, **k: solved.append(original(*a, **k)) or solved[-1])
    assert main(["solve", "--json", "--in-process", "--clips", str(folder)]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(rows) == 1 and len(solved) == 1
    row, clip = rows[0], solved[0]
    assert row["model"] == "sfm" and row["registered"] == "16/16", row
    # rotations: R_i R_0^T is the same in every gauge (a similarity changes each R by one right factor)
    Rs, Rg = clip.w2c[:, :3, :3], w2c[:, :3, :3]
    rel = lambda R: R @ R[0].T  # noqa: E731
    err = _angle_deg(np.einsum("fij,fkj->fik", rel(Rs), rel(Rg)))
    turn = _angle_deg(rel(Rg)).max()
    assert turn > 1.0 and err.max() < 0.5, (err.max(), turn)  # the camera turns; the solve follows
    # the printed figures are this solve's
    digest = hashlib.sha256()
    for arr in (clip.w2c, clip.K, clip.points):
        digest.update(np.ascontiguousarray(arr, np.float64).tobytes())
    assert row["sha256"] == digest.hexdigest()[:16]
    C = -np.einsum("fji,fj->fi", clip.w2c[:, :3, :3], clip.w2c[:, :3, 3])
    assert row["path_length"] == pytest.approx(np.linalg.norm(np.diff(C, axis=0), axis=1).sum(), rel=1e-9)
    assert row["path_length"] > 0 and row["points"] == len(clip.points)
