"""Held-out quality of node initialisers x motion models on synthetic vrig scenes.

Examples::

    python -m engine.bench quality                          # small scenes, seeds 0 and 1
    python -m engine.bench quality --steps 150 --json
    python -m engine.bench quality data/clip --configs mani+spline,fps+mlp

For each scene (generated with ``tools/synth_scene.py`` when none is given) and each
``init+motion`` configuration, ``python -m engine train`` runs in a subprocess (so its peak
RSS is measured on its own, with ``os.wait4``) at the ``preview`` preset (``--steps``
overrides the step count for quick runs). Configurations of one scene share one priors
cache, so priors are computed once per scene. The held-out PSNR/SSIM come from the
training run's final evaluation (the trained model itself); ``psnr_bundle`` re-renders
the written bundle from disk (``engine eval``), which for ``mlp`` motion is the exported
spline approximation of the MLP. ``lpips`` is always null here (no bundled LPIPS model).

``--train-seeds 0,1,2`` trains every configuration once per training seed and appends a
``mean`` row per scene and configuration with ``psnr_std`` (the same configuration spreads
by ~0.1-0.2 dB over training seeds on the generated scenes, so single-seed differences
of that size rank nothing). ``--oracle depth,mask,tracks`` trains on the generated scene's
ground-truth priors (:mod:`engine.bench.oracle`) instead of the weight-free ones.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from .common import run_child

HELP = "held-out PSNR/SSIM of node init x motion configs (MANI/FPS/voxel x spline/mlp)"

DEFAULT_CONFIGS = "mani+spline,fps+spline,fps+mlp,voxel+spline"
REPO = Path(__file__).resolve().parents[2]


def add_arguments(parser):
    parser.add_argument("scenes", nargs="*", help="clip folders (default: generate synthetic scenes, seeds 0 and 1)")
    parser.add_argument("--preset", default="small", choices=("tiny", "small"),
                        help="synthetic scene preset when generating (default small)")
    parser.add_argument("--seeds", default="0,1", help="seeds of the generated scenes (default 0,1)")
    parser.add_argument("--steps", type=int, help="training steps (default: the preview preset's)")
    parser.add_argument("--configs", default=DEFAULT_CONFIGS, help=f"init+motion list (default {DEFAULT_CONFIGS})")
    parser.add_argument("--work", help="folder for generated scenes, priors caches and bundles "
                                       "(default: <tmp>/motion_splats_bench/quality)")
    parser.add_argument("--threads", type=int, help="CPU threads per training run")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), help="training device (default: the preset's, auto)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="training runs at a time (default 1; >1 only on a machine with cores/GPU to spare, "
                             "and then train_s/its_per_s/peak_rss_mb are measured under that load)")
    parser.add_argument("--config", help="JSON file of TrainConfig overrides passed to every training run")
    parser.add_argument("--train-seeds", default="",
                        help="comma list of training seeds (e.g. 0,1,2): every configuration trains once per seed "
                             "and a 'mean' row per scene and configuration follows (psnr_std = spread over seeds); "
                             "differences between configurations below that spread are noise")
    parser.add_argument("--oracle", default="",
                        help="generated scenes only: train on ground-truth priors instead of the weight-free ones, "
                             "a comma list of depth,mask,tracks (engine/bench/oracle.py); separates what the method "
                             "does from what the priors give it")


def generate_scene(out: Path, preset: str, seed: int) -> Path:
    """Generate (or reuse) a synthetic scene with tools/synth_scene.py."""
    if (out / "dataset.json").is_file():
        return out
    cmd = [sys.executable, str(REPO / "tools" / "synth_scene.py"), "--out", str(out), "--preset", preset,
           "--seed", str(seed), "--quiet"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"synth_scene failed ({proc.returncode}): {proc.stderr[-2000:]}")
    last = proc.stdout.strip().splitlines()[-1]
    return Path(json.loads(last)["out"])


def train_subprocess(clip, out, init: str, motion: str, cache, steps=None, threads=None, device=None,
                     config=None, priors=None, seed=None) -> dict:
    """Run ``python -m engine train`` in a child; returns its result event plus wall_s, peak_rss_mb."""
    cmd = [sys.executable, "-m", "engine", "train", str(clip), "--out", str(out), "--init", init, "--motion", motion,
           "--cache", str(cache), "--overwrite", "--jsonl", "--preset", "preview"]
    if steps:
        cmd += ["--steps", str(steps)]
    if threads:
        cmd += ["--threads", str(threads)]
    if device:
        cmd += ["--device", device]
    if config:
        cmd += ["--config", str(config)]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    for key, path in (priors or {}).items():  # precomputed priors, e.g. {"depth_path": ...}
        cmd += ["--" + key.replace("_", "-"), str(path)]
    out_text, err_text, code, wall, rss = run_child(cmd, REPO)
    result, error = None, None
    for line in out_text.splitlines():
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        if isinstance(ev, dict) and ev.get("event") == "result":
            result = ev
        elif isinstance(ev, dict) and ev.get("event") == "error":
            error = ev
    if code != 0 or result is None:
        msg = (error or {}).get("message") or err_text[-1500:]
        raise RuntimeError(f"train {init}+{motion} on {clip} failed ({code}): {msg}")
    return {**result, "wall_s": wall, "peak_rss_mb": rss}


def run_one(clip, name: str, init: str, motion: str, work: Path, steps=None, threads=None, device=None,
            config=None, priors=None, seed=None) -> dict:
    from ..bundle import read_scene
    from ..commands.eval import evaluate_bundle

    out = work / "bundles" / (f"{name}_{init}_{motion}" + ("" if seed is None else f"_seed{seed}"))
    res = train_subprocess(clip, out, init, motion, work / "cache" / name, steps, threads, device, config, priors,
                           seed)
    stats = read_scene(out / "scene.json").get("stats", {})
    ev, ev0 = res.get("eval") or {}, res.get("eval_init") or {}
    try:  # `engine train` writes eval.json with its report; evaluate only when it did not
        bundle_eval = json.loads((out / "eval.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        bundle_eval = evaluate_bundle(out, clip, write=True)
    return {"scene": name, "init": init, "motion": motion, **({} if seed is None else {"train_seed": seed}),
            "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": None,
            "psnr_init": ev0.get("psnr"), "ssim_init": ev0.get("ssim"),
            "psnr_bundle": bundle_eval["mean"]["psnr"], "masked_psnr": bundle_eval["mean"]["masked_psnr"],
            "steps": res.get("steps"), "train_s": stats.get("train_seconds"),
            "its_per_s": res.get("iterations_per_s"), "wall_s": round(res["wall_s"], 1),
            "gaussians": res.get("gaussians"), "nodes": res.get("nodes"),
            "peak_rss_mb": round(res["peak_rss_mb"], 1)}


def run(args) -> list[dict]:
    work = Path(args.work) if args.work else Path(tempfile.gettempdir()) / "motion_splats_bench" / "quality"
    work.mkdir(parents=True, exist_ok=True)
    configs = [c.strip().split("+") for c in args.configs.split(",") if c.strip()]
    for c in configs:
        if len(c) != 2:
            raise SystemExit(f"bad config {'+'.join(c)!r}: use init+motion, e.g. mani+spline")
    if args.scenes:
        scenes = [(Path(s).name, Path(s)) for s in args.scenes]
    else:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
        scenes = [(f"{args.preset}_seed{s}", generate_scene(work / f"{args.preset}_seed{s}", args.preset, s))
                  for s in seeds]
    oracle = sorted({k.strip() for k in (args.oracle or "").split(",") if k.strip()})
    priors = {}
    if oracle:
        from .oracle import write_oracle_priors

        tag = "oracle_" + "_".join(oracle)
        for name, clip in scenes:
            priors[name] = write_oracle_priors(clip, work / tag / name, oracle)
        scenes = [(f"{name}+{tag}", clip) for name, clip in scenes]  # own bundles and priors cache
        priors = {f"{name}+{tag}": p for name, p in priors.items()}
    seeds = [int(x) for x in args.train_seeds.split(",") if x.strip()] or [None]
    jobs = [(name, clip, init, motion, seed) for name, clip in scenes for init, motion in configs for seed in seeds]

    def one(job):
        name, clip, init, motion, seed = job
        row = run_one(clip, name, init, motion, work, args.steps, args.threads, args.device, args.config,
                      priors.get(name), seed)
        print(json.dumps({"progress": row}), file=sys.stderr, flush=True)
        return row

    if args.jobs <= 1:
        rows = [one(j) for j in jobs]
    else:
        from concurrent.futures import ThreadPoolExecutor  # the runs are subprocesses: threads only wait
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            rows = list(pool.map(one, jobs))
    return rows + (seed_means(rows) if len(seeds) > 1 else [])


def seed_means(rows: list[dict]) -> list[dict]:
    """One ``train_seed = 'mean'`` row per (scene, init, motion): the mean of every metric over
    the training seeds and ``psnr_std``, their standard deviation (ddof 1)."""
    import statistics

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["init"], r["motion"]), []).append(r)
    out = []
    for (scene, init, motion), rs in groups.items():
        row = {"scene": scene, "init": init, "motion": motion, "train_seed": "mean"}
        for key in ("psnr", "ssim", "psnr_init", "masked_psnr", "train_s", "its_per_s", "nodes"):
            vals = [r[key] for r in rs if isinstance(r.get(key), (int, float))]
            row[key] = statistics.fmean(vals) if vals else None
        ps = [r["psnr"] for r in rs if isinstance(r.get("psnr"), (int, float))]
        row["psnr_std"] = statistics.stdev(ps) if len(ps) > 1 else None
        out.append(row)
    return out
