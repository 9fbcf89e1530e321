"""Cycles render of the Blender preview vs the engine's own render of the same frame.

Examples::

    python -m engine.bench cycles                         # quick training of data/demo_clip first
    python -m engine.bench cycles out/run --frames 1,16,32 --samples 32 --json
    python -m engine.bench cycles --clip data/other --steps 300

The trained bundle (given, or trained here from ``--clip`` at the ``preview`` preset, as
``make demo`` does) is rendered twice at the same scene frames:

* by the engine (``python -m engine render BUNDLE --frames ...``: the bundle's training
  camera nearest each frame, the rasteriser);
* by Cycles on the CPU (``tools/bpy_scene.py cycles``, a child process with this
  interpreter's ``bpy``): the add-on builds the bundle (Empties + F-curves, DQS rig,
  ellipsoid preview with the Gaussian-falloff material, animated camera following the
  training cameras) and renders those frames.

One row per frame with the PSNR between the two 8-bit images (goal ≥ 25 dB, issue #7),
plus a ``mean`` row. The renders stay in ``--work`` for a look.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HELP = "PSNR of the Cycles render of the Blender preview vs the engine render (same frame and camera)"

REPO = Path(__file__).resolve().parents[2]
GOAL_DB = 25.0


def add_arguments(parser):
    parser.add_argument("bundle", nargs="?", help="trained bundle (default: train --clip at the preview preset)")
    parser.add_argument("--clip", default=str(REPO / "data" / "demo_clip"),
                        help="clip to train when no bundle is given (default: the bundled demo clip)")
    parser.add_argument("--steps", type=int, help="training steps (default: the preview preset's)")
    parser.add_argument("--frames", help="scene frames to compare, e.g. 1,16,32 (default: first, middle, last)")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    parser.add_argument("--work", help="folder for the trained bundle and the renders "
                                       "(default: <tmp>/motion_splats_bench/cycles)")
    parser.add_argument("--threads", type=int, help="CPU threads for the training run")


def psnr_files(a_path, b_path) -> float | None:
    """PSNR (dB) between two 8-bit image files; ``a`` is resized to ``b`` when sizes differ.

    ``None`` when either file cannot be read.
    """
    import cv2
    import numpy as np

    a, b = cv2.imread(str(a_path)), cv2.imread(str(b_path))
    if a is None or b is None:
        return None
    if a.shape != b.shape:
        a = cv2.resize(a, (b.shape[1], b.shape[0]), interpolation=cv2.INTER_AREA)
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float(10 * np.log10(255.0 ** 2 / max(mse, 1e-12)))


def default_frames(scene: dict) -> list[int]:
    tm = scene["time"]
    fs, fe = int(tm["frame_start"]), int(tm["frame_end"])
    return sorted({fs, (fs + fe) // 2, fe})


def engine_render(bundle, frames, out_dir) -> list[Path]:
    """``python -m engine render`` of ``frames`` into ``out_dir`` (replaced); returns the PNG paths."""
    cmd = [sys.executable, "-m", "engine", "render", str(bundle), "--frames", ",".join(map(str, frames)),
           "--out", str(out_dir), "--overwrite", "--quiet"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"engine render failed ({proc.returncode}): {proc.stderr[-1500:]}")
    return [Path(out_dir) / f"frame_{int(f):05d}.png" for f in frames]


def run(args) -> list[dict]:
    from ..bundle import load_bundle
    from .build import run_bpy

    work = Path(args.work) if args.work else Path(tempfile.gettempdir()) / "motion_splats_bench" / "cycles"
    work.mkdir(parents=True, exist_ok=True)
    train = {}
    if args.bundle:
        bundle = Path(args.bundle)
    else:
        from .quality import train_subprocess

        bundle = work / "bundle"
        res = train_subprocess(args.clip, bundle, "mani", "spline", work / "cache", args.steps, args.threads)
        train = {"train_steps": res.get("steps"), "train_wall_s": round(res["wall_s"], 1)}
    b = load_bundle(bundle)
    if b.gaussians is None:
        raise SystemExit(f"{bundle}: the bundle has no trained Gaussians; train it first (python -m engine train)")
    frames = ([int(f) for f in args.frames.split(",") if f.strip()] if args.frames else default_frames(b.scene))
    t0 = time.perf_counter()
    engine_pngs = engine_render(bundle, frames, work / "engine")
    engine_s = time.perf_counter() - t0
    res, wall, rss = run_bpy(["cycles", bundle, "--frames", ",".join(map(str, frames)), "--out", work / "cycles",
                              "--samples", args.samples])
    common = {"samples": args.samples, "width": res["width"], "height": res["height"],
              "gaussians": res["build"]["gaussians"], "nodes": res["build"]["nodes"],
              "build_s": res["build"]["timings"].get("total"),
              "bundle_steps": (b.scene.get("stats") or {}).get("steps"), **train}
    rows = []
    for f, cyc, eng, secs in zip(frames, res["cycles"], engine_pngs, res["render_s"]):
        psnr = psnr_files(cyc, eng)
        rows.append({"frame": f, "psnr_db": None if psnr is None else round(psnr, 2), "goal_db": GOAL_DB,
                     "meets_goal": psnr is not None and psnr >= GOAL_DB, "cycles_s": secs, **common})
    vals = [r["psnr_db"] for r in rows if r["psnr_db"] is not None]
    mean = round(sum(vals) / len(vals), 2) if vals else None
    rows.append({"frame": "mean", "psnr_db": mean, "goal_db": GOAL_DB,
                 "meets_goal": mean is not None and mean >= GOAL_DB,
                 "cycles_s": round(sum(res["render_s"]), 2), **common,
                 "engine_render_s": round(engine_s, 2), "blender_wall_s": round(wall, 2),
                 "blender_peak_rss_mb": round(rss, 1), "cores": os.cpu_count(),
                 "load_1m": round(os.getloadavg()[0], 2), "bundle": str(bundle), "renders": str(work)})
    print(json.dumps({"progress": rows[-1]}), file=sys.stderr, flush=True)
    return rows
