"""Camera-solve repeatability and model choice on clips without cameras.

Each clip is solved ``--repeats`` times, every time in a fresh child process (what a user re-running
``engine train`` gets), the way ``engine.pipeline.open_clip`` solves it (at most 60 sampled frames,
camera-free masks, evidence-based model choice, global-SfM retry, fixed-centre fallback). One row per
clip: the chosen model, ``distinct`` (how many different camera sets the repeats produced: 1 =
deterministic), quality (registered frames, reprojection / transfer error, sparse points, parallax
evidence) and wall time. Default clips: ``../shared/data/clips/{cups,bedroom}.mp4`` when present.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

from .common import run_child

HELP = "camera solve: model chosen and repeatability over fresh processes (clips without cameras)"
SHARED_CLIPS = Path(__file__).resolve().parents[3] / "shared" / "data" / "clips"


def add_arguments(parser) -> None:
    parser.add_argument("--clips", nargs="+", help="clips to solve (default: ../shared/data/clips/cups.mp4, "
                                                   "bedroom.mp4)")
    parser.add_argument("--repeats", type=int, default=5, help="solves per clip, each in a fresh process")
    parser.add_argument("--in-process", action="store_true", help=argparse.SUPPRESS)  # one child's work


def solve_once(path) -> dict:
    """Solve ``path`` as ``open_clip`` does; the camera fingerprint and the solve record."""
    from ..io.solve_select import summary
    from ..pipeline import open_clip

    t0 = time.perf_counter()
    clip = open_clip(path, solve=True)
    digest = hashlib.sha256()
    for arr in (clip.w2c, clip.K, clip.points):
        if arr is not None:
            digest.update(np.ascontiguousarray(arr, np.float64).tobytes())
    C = clip.camera_centers()
    rec = summary(clip.meta["solve"])
    return {"clip": Path(path).name, "sha256": digest.hexdigest()[:16], "model": rec["model"],
            "mapper": rec.get("mapper"), "registered": f"{rec['num_registered']}/{rec['num_frames']}",
            "error_px": rec["mean_reproj_error"], "points": rec["num_points"], "parallax_px": rec.get("parallax_px"),
            "floor_px": rec.get("parallax_floor_px"),
            "path_length": float(np.linalg.norm(np.diff(C, axis=0), axis=1).sum()),
            "time_s": time.perf_counter() - t0}


def run(args) -> list[dict]:
    from ..errors import InputError

    clips = args.clips or [str(SHARED_CLIPS / n) for n in ("cups.mp4", "bedroom.mp4")]
    missing = [c for c in clips if not Path(c).exists()]
    if missing:
        raise InputError("clip not found", missing[0], "pass --clips PATH ... (the default clips live in "
                                                       "../shared/data/clips)")
    if args.in_process:
        return [solve_once(c) for c in clips]
    rows = []
    for c in clips:
        runs = []
        for _ in range(max(1, int(args.repeats))):
            out, err, code, wall, _ = run_child([sys.executable, "-m", "engine.bench", "solve", "--json",
                                                 "--in-process", "--clips", str(Path(c).resolve())],
                                                cwd=Path(__file__).resolve().parents[2])
            if code != 0:
                raise RuntimeError(f"solve of {c} failed: {err.strip().splitlines()[-1] if err.strip() else code}")
            runs.append(json.loads(out.strip().splitlines()[-1]))
        row = dict(runs[0])
        row["repeats"] = len(runs)
        row["distinct"] = len({r["sha256"] for r in runs})
        row["models"] = ",".join(sorted({r["model"] for r in runs}))
        row["time_s"] = float(np.median([r["time_s"] for r in runs]))
        rows.append(row)
    return rows
