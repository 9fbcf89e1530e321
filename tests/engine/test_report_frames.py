"""The report's training-frame section (issue #17): a contact sheet of training frames
spread over the clip and the node overlay at several times."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from engine.report_frames import spread

REPO = Path(__file__).resolve().parents[2]


def test_spread_picks_first_last_and_evenly_between():
    assert spread(list(range(60)), 6) == [0, 12, 24, 35, 47, 59]
    assert spread([3, 4], 6) == [3, 4] and spread([], 4) == []


@pytest.mark.slow
def test_report_shows_training_frames_spread_over_the_clip(tmp_path):
    """~40 s: a 3-step run on the tiny generated scene, then `engine report`."""
    pytest.importorskip("bpy")
    import cv2

    from engine.bundle import load_bundle
    from engine.commands.eval import _camera_frame, _open_clip_for
    from engine.report_frames import OVERLAY_TIMES, SHEET_FRAMES, training_cameras

    gen = subprocess.run([sys.executable, "tools/synth_scene.py", "--out", str(tmp_path / "clip"), "--preset", "tiny",
                          "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=180)
    assert gen.returncode == 0, gen.stderr[-2000:]
    out = tmp_path / "bundle"
    tr = subprocess.run([sys.executable, "-m", "engine", "train", str(tmp_path / "clip"), "--out", str(out),
                         "--steps", "3", "--jsonl", "--cache", str(tmp_path / "cache")],
                        cwd=REPO, capture_output=True, text=True, timeout=300)
    assert tr.returncode == 0, tr.stdout[-2000:] + tr.stderr[-2000:]
    html = (out / "report" / "report.html").read_text(encoding="utf-8")
    assert 'src="contact_sheet.png"' in html and 'src="nodes_overlay.png"' in html
    sheet = cv2.imread(str(out / "report" / "contact_sheet.png"))[..., ::-1]
    bundle = load_bundle(out)
    cams = training_cameras(bundle.scene)
    assert len(cams) > SHEET_FRAMES  # so the pick is a real spread, not every frame
    w, h, gap = int(cams[0]["width"]), int(cams[0]["height"]), 2
    assert sheet.shape == (SHEET_FRAMES * (h + gap) - gap, 3 * w + 2 * gap, 3)
    # the ground-truth column is the clip's training frames: first, last and evenly between
    clip, path = _open_clip_for(bundle, None)
    start = int(clip.meta.get("frame_start", 1))
    frames = [_camera_frame(clip, c, start, path)[1] for c in cams]
    rows = [sheet[r * (h + gap):r * (h + gap) + h, :w] for r in range(SHEET_FRAMES)]
    picked = [int(np.argmin([np.abs(r.astype(int) - f).mean() for f in frames])) for r in rows]
    assert picked == spread(list(range(len(cams))), SHEET_FRAMES)
    assert all(np.array_equal(r, frames[i]) for r, i in zip(rows, picked))
    # the render column differs from the ground truth (3 steps) and the error column shows it
    assert not np.array_equal(sheet[:h, w + gap:2 * w + gap], rows[0])
    assert sheet[:h, 2 * (w + gap):].mean() > 0
    # the node overlay: one panel per time, each at its frame's time
    ov = cv2.imread(str(out / "report" / "nodes_overlay.png"))
    assert ov.shape[:2] == (h, OVERLAY_TIMES * w + (OVERLAY_TIMES - 1) * 4)
    for c in spread(cams, OVERLAY_TIMES):
        assert f"{c['frame']} (time {float(c['time']):.3f})" in html
