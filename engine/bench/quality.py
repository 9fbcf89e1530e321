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

Every row also carries the measures that make a lost moving object visible (issue #17):
``psnr/ssim/masked_psnr/masked_ssim`` with suffix ``_train`` (``engine eval --split train``:
the bundle at its own training cameras) and ``_val`` (held-out cameras; ``masked_*`` only
when the scene has dynamic masks), the still-plate baseline of the training frames
(``plate_psnr``, ``plate_masked_psnr``: the median training frame scored against every
training frame, :mod:`engine.bench.still_plate`) and, on generated scenes, the node
trajectories after training vs ground truth (``traj_err_dyn``, ``zero_motion_dyn``,
``traj_ratio_dyn`` = their ratio; ``rot_err_dyn_deg`` against ``rot_gt_dyn_deg``, how the nodes on
moving objects turn against the objects' own turn, :mod:`engine.bench.node_motion`) and
``kept_dyn``, the share of the Gaussians on a moving object at the middle training frame still on
it at the others (:mod:`engine.bench.object_coverage`: low when each stretch of time has its own
Gaussians for the object). ``--kind large``
generates the large-motion family (60 frames).

``--train-seeds 0,1,2`` trains every configuration once per training seed and appends a
``mean`` row per scene and configuration with ``psnr_std`` (the same configuration spreads
by ~0.1-0.2 dB over training seeds on the generated scenes, so single-seed differences
of that size rank nothing). With two configurations or more and two (scene, seed) cells or
more, ``paired`` rows follow: for every pair of configurations the mean difference of
``masked_psnr_val`` over the cells both ran (scenes x training seeds), its paired t and p.
``--oracle depth,mask,tracks`` trains on the generated scene's
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
    parser.add_argument("--kind", choices=("all", "articulated", "large", "nonrigid", "rigid"),
                        help="generated scene family (tools/synth_scene.py --kind; default: the generator's own); "
                             "'large' (objects crossing most of the frame, a fast pendulum) renders 60 frames")
    parser.add_argument("--frames", type=int, help="frames of generated scenes (default: 60 with --kind large, "
                                                   "else the preset's)")
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
    parser.add_argument("--flow-backend", choices=("auto", "dis", "onnx"),
                        help="the trainings' optical flow (engine train --flow-backend; auto: the shipped "
                             "RAFT-small fused with DIS); the scenes' bundles and priors caches get a tag of their own")
    parser.add_argument("--depth-model", help="the trainings' ONNX depth model (engine train --depth-model), with "
                                              "--depth-output, --depth-sidecar and --depth-check as there")
    parser.add_argument("--depth-output", choices=("inverse", "depth"))
    parser.add_argument("--depth-sidecar", metavar="JSON")
    parser.add_argument("--depth-check", choices=("auto", "off"))
    parser.add_argument("--oracle", default="",
                        help="generated scenes only: train on ground-truth priors instead of the weight-free ones, "
                             "a comma list of depth,mask,tracks (engine/bench/oracle.py); separates what the method "
                             "does from what the priors give it")


def generate_scene(out: Path, preset: str, seed: int, kind: str | None = None, frames: int | None = None) -> Path:
    """Generate (or reuse) a synthetic scene with tools/synth_scene.py."""
    if (out / "dataset.json").is_file():
        return out
    cmd = [sys.executable, str(REPO / "tools" / "synth_scene.py"), "--out", str(out), "--preset", preset,
           "--seed", str(seed), "--quiet"]
    cmd += ["--kind", kind] if kind else []
    cmd += ["--frames", str(frames)] if frames else []
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
        msg = (error or {}).get("message") or ""
        if not msg or msg.startswith("internal error"):  # the child's traceback is on its stderr
            msg = (msg + "\n" + err_text[-3000:]).strip()
        raise RuntimeError(f"train {init}+{motion} on {clip} failed ({code}): {msg}")
    return {**result, "wall_s": wall, "peak_rss_mb": rss}


def _masked(ev: dict, suffix: str) -> dict:
    """``psnr/ssim/masked_psnr/masked_ssim`` of an ``engine eval`` mean, keys suffixed."""
    m = ev.get("mean") or {}
    return {f"{k}{suffix}": m.get(k) for k in ("psnr", "ssim", "masked_psnr", "masked_ssim")}


def scene_baselines(bundle_dir, clip) -> dict:
    """Per-scene figures that do not depend on the configuration: the still plate of the
    training frames (:mod:`engine.bench.still_plate`), whole image and masked."""
    from .still_plate import bundle_split_frames, still_plate_scores

    frames, masks = bundle_split_frames(bundle_dir, "train", clip)
    s = still_plate_scores(frames, masks)
    return {"plate_psnr": s["plate_psnr"], "plate_masked_psnr": s["plate_masked_psnr"]}


def node_motion(bundle_dir, clip) -> dict:
    """Node-trajectory error after training and the Gaussians kept on the moving objects
    (generated scenes with ``gt/trajectories.npz`` / ``gt/objects.json``)."""
    if not (Path(clip) / "gt" / "trajectories.npz").is_file():
        return {"traj_err_dyn": None, "zero_motion_dyn": None, "traj_ratio_dyn": None, "rot_err_dyn_deg": None,
                "rot_gt_dyn_deg": None, "kept_dyn": None}
    from .node_motion import trained_trajectory_error
    from .object_coverage import kept_on_objects

    t = trained_trajectory_error(bundle_dir, clip)
    kept = kept_on_objects(bundle_dir, clip) if (Path(clip) / "gt" / "objects.json").is_file() else {}
    return {**{k: t[k] for k in ("traj_err_dyn", "zero_motion_dyn", "traj_ratio_dyn", "rot_err_dyn_deg",
                                 "rot_gt_dyn_deg")}, "kept_dyn": kept.get("kept_dyn")}


def run_one(clip, name: str, init: str, motion: str, work: Path, steps=None, threads=None, device=None,
            config=None, priors=None, seed=None, baselines: dict | None = None) -> dict:
    """Train one configuration and measure it; ``baselines`` caches :func:`scene_baselines`
    per scene name (the still plate depends on the scene only)."""
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
    train_eval = evaluate_bundle(out, clip, split="train", write=False)
    if baselines is None or name not in baselines:
        base = scene_baselines(out, clip)
        if baselines is not None:
            baselines[name] = base
    else:
        base = baselines[name]
    return {"scene": name, "init": init, "motion": motion, **({} if seed is None else {"train_seed": seed}),
            "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": None,
            "psnr_init": ev0.get("psnr"), "ssim_init": ev0.get("ssim"),
            "psnr_bundle": bundle_eval["mean"]["psnr"], "masked_psnr": bundle_eval["mean"]["masked_psnr"],
            **_masked(train_eval, "_train"), **_masked(bundle_eval, "_val"), **base,
            **node_motion(out, clip),
            "steps": res.get("steps"), "train_s": stats.get("train_seconds"),
            "its_per_s": res.get("iterations_per_s"), "wall_s": round(res["wall_s"], 1),
            "gaussians": res.get("gaussians"), "nodes": res.get("nodes"),
            "peak_rss_mb": round(res["peak_rss_mb"], 1)}


#: engine train's prior options the bench passes on, each with its part of the scenes' tag
_PRIOR_TAGS = {"flow_backend": lambda v: f"flow-{v}", "depth_model": lambda v: f"depth-{Path(str(v)).stem}",
               "depth_output": lambda v: f"out-{v}", "depth_sidecar": lambda v: "side",
               "depth_check": lambda v: f"check-{v}"}
LEARNED_PRIOR_OPTIONS = tuple(_PRIOR_TAGS)


def learned_prior_options(args) -> dict:
    """The prior options given to the bench, as ``{option name: value}`` for ``engine train``
    (:func:`train_subprocess` turns ``depth_model`` into ``--depth-model``)."""
    return {k: getattr(args, k) for k in LEARNED_PRIOR_OPTIONS if getattr(args, k, None)}


def learned_prior_tag(options: dict) -> str:
    """A short name for a run's prior options (its bundles' and caches' folder suffix), e.g.
    ``flow-auto`` or ``depth-pydnet_out-depth_side_check-off``."""
    return "_".join(_PRIOR_TAGS[key](value) for key, value in options.items())


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
        kind = getattr(args, "kind", None)
        frames = getattr(args, "frames", None) or (60 if kind == "large" else None)
        tag = args.preset if not kind else f"{kind}_{args.preset}" + (f"_{frames}f" if frames else "")
        scenes = [(f"{tag}_seed{s}", generate_scene(work / f"{tag}_seed{s}", args.preset, s, kind, frames))
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
    learned = learned_prior_options(args)
    if learned:
        tag = learned_prior_tag(learned)
        priors = {f"{name}+{tag}": {**priors.get(name, {}), **learned} for name, _ in scenes}
        scenes = [(f"{name}+{tag}", clip) for name, clip in scenes]  # own bundles and priors cache
    seeds = [int(x) for x in args.train_seeds.split(",") if x.strip()] or [None]
    jobs = [(name, clip, init, motion, seed) for name, clip in scenes for init, motion in configs for seed in seeds]

    baselines: dict = {}

    def one(job):
        name, clip, init, motion, seed = job
        row = run_one(clip, name, init, motion, work, args.steps, args.threads, args.device, args.config,
                      priors.get(name), seed, baselines)
        print(json.dumps({"progress": row}), file=sys.stderr, flush=True)
        return row

    if args.jobs <= 1:
        rows = [one(j) for j in jobs]
    else:
        from concurrent.futures import ThreadPoolExecutor  # the runs are subprocesses: threads only wait
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            rows = list(pool.map(one, jobs))
    # paired rows whenever two configurations share at least two (scene, seed) cells
    paired = paired_stats(rows) if len(configs) > 1 and len(scenes) * len(seeds) > 1 else []
    return rows + (seed_means(rows) if len(seeds) > 1 else []) + paired


MEAN_KEYS = ("psnr", "ssim", "psnr_init", "masked_psnr", "psnr_train", "masked_psnr_train", "masked_ssim_train",
             "masked_psnr_val", "masked_ssim_val", "plate_psnr", "plate_masked_psnr", "traj_err_dyn",
             "zero_motion_dyn", "traj_ratio_dyn", "kept_dyn", "train_s", "its_per_s", "nodes")


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
        for key in MEAN_KEYS:
            vals = [r[key] for r in rs if isinstance(r.get(key), (int, float))]
            row[key] = statistics.fmean(vals) if vals else None
        ps = [r["psnr"] for r in rs if isinstance(r.get("psnr"), (int, float))]
        row["psnr_std"] = statistics.stdev(ps) if len(ps) > 1 else None
        mv = [r["masked_psnr_val"] for r in rs if isinstance(r.get("masked_psnr_val"), (int, float))]
        row["masked_psnr_val_std"] = statistics.stdev(mv) if len(mv) > 1 else None
        out.append(row)
    return out


def paired_stats(rows: list[dict], metric: str = "masked_psnr_val") -> list[dict]:
    """Paired comparison of configurations over (scene, training seed) on ``metric``.

    For every pair of configurations (in first-seen order), the differences ``b − a`` over
    the (scene, train_seed) cells both ran give ``mean_diff``, ``sd_diff`` (ddof 1) and the
    paired ``t = mean_diff / (sd_diff / sqrt(n))`` with its two-sided ``p`` (Student t,
    n − 1 degrees of freedom; None when n < 2 or the differences do not vary).
    """
    import itertools
    import math
    import statistics

    cells: dict[tuple, dict] = {}
    for r in rows:
        if r.get("train_seed") == "mean" or not isinstance(r.get(metric), (int, float)):
            continue
        cells.setdefault((r["init"], r["motion"]), {})[(r["scene"], r.get("train_seed"))] = r[metric]
    out = []
    for a, b in itertools.combinations(list(cells), 2):
        keys = sorted(set(cells[a]) & set(cells[b]), key=str)
        d = [cells[b][k] - cells[a][k] for k in keys]
        n = len(d)
        mean = statistics.fmean(d) if d else None
        sd = statistics.stdev(d) if n > 1 else None
        t = p = None
        if sd:
            t = mean / (sd / math.sqrt(n))
            from scipy.stats import t as student_t

            p = float(2 * student_t.sf(abs(t), n - 1))
        out.append({"scene": "paired", "a": "+".join(a), "b": "+".join(b), "metric": metric, "n": n,
                    "mean_diff": mean, "sd_diff": sd, "t": t, "p": p})
    return out
