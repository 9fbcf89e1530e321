"""Training throughput: iterations/s of the full training step, with a per-phase breakdown.

Examples::

    python -m engine.bench train                      # preview preset, 240x180, ~30k Gaussians, ~1k nodes
    python -m engine.bench train --steps 100 --repeats 3 --json
    python -m engine.bench train --clip data/demo_clip  # a real clip through the pipeline front end
    python -m engine.bench train --device cuda --gaussians 200000 --width 480   # on a GPU
    python -m engine.bench train --repeats 8 --baseline ../base   # paired against another tree

What is measured
----------------
One row per repeat; each repeat runs in a fresh subprocess (its own peak RSS, the same
thread settings as ``python -m engine``: ``OMP_WAIT_POLICY=PASSIVE``, torch's default
thread count unless ``--threads``). The step is the real :class:`engine.train.trainer.Trainer`
step at the ``preview`` preset with deformation on: spline motion (fused DQB), all default
losses (L1 + D-SSIM, mask every 4th step as an extra channel of the colour pass, depth,
track, ARAP, velocity/acceleration) and the per-step densification statistics.
``--device cuda`` runs the same step on a GPU
(``backend='auto'``: gsplat when it imports); the timed window then ends with a
``torch.cuda.synchronize()``, but the per-phase columns time kernel *launches* (CUDA runs
asynchronously), so on CUDA only ``its_per_s``/``ms_step`` are wall-clock truths. The trainer starts *after* the static warm-up and
inside the densification window (step ``densify_from + 1``), so motion, track and ARAP
terms are all live; ``--warmup`` untimed steps come first (Numba cache loads, allocator
warm-up), then ``--steps`` timed steps. Densification events, rebinding and checkpoints
are kept out of the timed window and reported on their own: ``densify_ms`` is one
``Trainer._densify()`` call (clone/split/prune, node densification, graph and binding
rebuild) after the timed steps; ``its_per_s_amortised`` spreads it over
``densify_every`` steps as a real preview run does between ``densify_from`` and
``densify_until``.

Columns: ``its_per_s`` (timed steps / wall s), ``ms_step``, ``cpu_ms_step`` (process CPU
time per step, all threads; on a shared machine it is steadier than wall time), the
per-phase wall ms per step ``deform`` (node splines + fused DQB forward), ``sh`` (SH ->
colour), ``raster_fwd`` (project + rasterise, with the mask term's extra channel every
4th step), ``losses`` (every loss term incl. the track/ARAP deformations, metrics), ``backward`` (all of autograd) split
into ``bwd_raster`` (the CPU rasteriser's project + rasterise backward), ``bwd_deform``
(the fused DQB backward) and ``bwd_torch`` (the rest: SH, losses, splines, glue),
``optimizer`` (Adam step), ``densify_stats`` (2D-gradient accumulation) and ``other``
(frame sampling, LR schedule, zero_grad, logging: the step's wall time minus the phases),
the same phases' process CPU ms per step as ``cpu_<phase>``, plus ``load_1m``
(``/proc/loadavg`` at the end of the row) to read figures taken on a shared machine.

``--baseline DIR`` times another tree of the project (a ``git worktree`` or an export of its
``engine/``) with the same interpreter: each repeat is a pair of rows, one per tree (tagged
``tree`` = ``head`` / ``baseline`` and ``pair``), the order alternating from pair to pair, and a
last row summarises them (``its_per_s_median`` of each, ``step_ratio_median`` / ``_min`` /
``_max`` of this tree's step time over the baseline's, pair by pair): on a machine whose speed
drifts between minutes, only rows taken side by side compare.

Scene (default, built in seconds and deterministic under ``--seed``): a textured wall that
fills the view plus a translating, rotating blob, rendered with the CPU rasteriser into
``--frames`` 240x180 frames from a swaying camera (every 8th frame held out), giving
images, depth, foreground masks and ground-truth 2D tracks; ``--nodes`` nodes on the
wall and in the blob (the blob's following its true motion); the model is initialised
by the trainer itself (back-projection) with ``--gaussians`` Gaussians. With ``--clip``
the clip goes through the real front end instead (``engine.pipeline``: frames, priors,
MANI nodes) before the same timing; priors are cached under ``--work``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .common import machine_description, peak_rss_mb

HELP = "training step throughput (it/s) at the preview preset with a per-phase breakdown"

PHASES = ("deform", "sh", "raster_fwd", "losses", "backward", "bwd_raster", "bwd_deform", "bwd_torch",
          "optimizer", "densify_stats", "other")


def add_arguments(parser) -> None:
    parser.add_argument("--clip", help="time a real clip through the pipeline front end instead of the synthetic scene")
    parser.add_argument("--width", type=int, default=240, help="training width (default 240 -> 240x180)")
    parser.add_argument("--gaussians", type=int, default=30_000, help="Gaussians of the synthetic scene's model")
    parser.add_argument("--nodes", type=int, default=1024, help="nodes of the synthetic scene")
    parser.add_argument("--frames", type=int, default=60, help="frames of the synthetic scene")
    parser.add_argument("--steps", type=int, default=60, help="timed training steps per repeat")
    parser.add_argument("--warmup", type=int, default=8, help="untimed steps before timing")
    parser.add_argument("--repeats", type=int, default=1, help="rows (fresh subprocesses)")
    parser.add_argument("--threads", type=int, default=None, help="torch/Numba threads (default: torch's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                        help="training device (default cpu; cuda uses the gsplat backend when it imports)")
    parser.add_argument("--work", help="folder for the --clip priors cache (default: <tmp>/motion_splats_bench/train)")
    parser.add_argument("--baseline", metavar="DIR",
                        help="another tree of this project (e.g. `git worktree add DIR REV`) to time against: each "
                             "repeat runs a row here and a row there, in alternating order, then a summary row of "
                             "the paired step-time ratios")
    parser.add_argument("--worker", help=__import__("argparse").SUPPRESS)  # internal: run one row in-process


# ----------------------------------------------------------------------------------
# Synthetic scene
# ----------------------------------------------------------------------------------
def render_observation(means, quats, scales, opacities, colors, dynamic, w2c, K, width: int, height: int,
                       backend: str = "auto"):
    """What a camera sees of a known Gaussian scene, as the priors would give it.

    ``dynamic [N, 3]`` is 1 on moving Gaussians and 0 elsewhere (rendered as colours).
    Returns ``(image [H, W, 3] in [0, 1], depth [H, W] (expected depth where alpha > 0.5,
    else 0), fg [H, W] in [0, 1])``. Shared by this bench's synthetic scene and the training
    tests' procedural scene.
    """
    import torch

    from .. import raster

    with torch.no_grad():
        out = raster.render(means, quats, scales, opacities, colors=colors, w2c=w2c, K=K, width=width,
                            height=height, background=torch.zeros(3), backend=backend)
        m = raster.render(means, quats, scales, opacities, colors=dynamic, w2c=w2c, K=K, width=width,
                          height=height, background=torch.zeros(3), backend=backend)
    depth = (out.depth / out.alpha.clamp_min(1e-6))[..., 0] * (out.alpha[..., 0] > 0.5)
    return out.rgb.clamp(0, 1), depth, m.rgb[..., 0].clamp(0, 1)


def synthetic_scene(width: int = 240, frames: int = 60, nodes: int = 1024, seed: int = 0):
    """A deterministic dynamic scene: ``(TrainingData, NodeArrays)``.

    A wall (y = 1.5, 8 x 6 units, ~20k true Gaussians with a colour texture) fills the view;
    a blob of ~3k Gaussians translates across it and turns about its vertical axis. The
    camera sways sideways; every 8th frame is a held-out view shifted by 0.4 units.
    Images / depth / foreground masks are CPU-rasteriser renders of the true scene at
    ``width x 3/4 width``; tracks are true points projected into every frame.
    """
    import numpy as np
    import torch

    from .. import bundle as B
    from ..geometry.camera import intrinsics, look_at, project
    from ..geometry.hermite import catmull_rom_tangents
    from ..geometry.quaternion import quat_apply, quat_from_axis_angle
    from ..nodes.graph import node_graph, node_radii
    from ..train.data import TrainingData

    height = width * 3 // 4
    g = torch.Generator().manual_seed(seed)
    nw, nb = 20_000, 3_000
    wall = torch.stack([torch.rand(nw, generator=g) * 8 - 4, torch.full((nw,), 1.5),
                        torch.rand(nw, generator=g) * 6 - 3], -1)
    wall_col = torch.stack([0.5 + 0.4 * torch.sin(5 * wall[:, 0]), 0.5 + 0.4 * torch.cos(4 * wall[:, 2]),
                            torch.rand(nw, generator=g) * 0.5 + 0.25], -1)
    blob = torch.randn(nb, 3, generator=g) * torch.tensor([0.35, 0.2, 0.25])
    blob_col = torch.stack([0.8 + 0.15 * torch.sign(blob[:, 0]), 0.3 + 0.2 * torch.sign(blob[:, 2]),
                            0.1 + 0.05 * torch.rand(nb, generator=g)], -1)
    axis = torch.tensor([0.0, 0.0, 1.0])

    def blob_motion(t):  # t [T] -> offset [T, 3], rotation [T, 4]
        off = torch.stack([-1.2 + 2.4 * t, torch.zeros_like(t), 0.4 * torch.sin(math.pi * t)], -1)
        return off, quat_from_axis_angle(axis.expand(len(t), 3), 1.2 * t)

    times = torch.linspace(0, 1, frames)
    K = intrinsics(0.9 * width, 0.9 * width, width / 2, height / 2, dtype=torch.float32)
    val = torch.arange(frames) % 8 == 7
    n_all = nw + nb
    quats = torch.zeros(n_all, 4)
    quats[:, 0] = 1
    scales = torch.cat([torch.full((nw, 3), 0.045), torch.full((nb, 3), 0.05)])
    op = torch.full((n_all,), 0.9)
    dyn = torch.cat([torch.zeros(nw, 3), torch.ones(nb, 3)])
    off, rot = blob_motion(times)
    w2cs, imgs, depths, fgs = [], [], [], []
    with torch.no_grad():
        for f in range(frames):  # one render per frame (seconds in all)
            sway = 0.8 * math.sin(2 * math.pi * float(times[f]))
            eye = torch.tensor([sway + (0.4 if val[f] else 0.0), -4.0, 0.3])
            w2c = look_at(eye, torch.tensor([0.0, 1.5, 0.0])).float()
            moved = quat_apply(rot[f].expand(nb, 4), blob) + off[f]
            means = torch.cat([wall, moved])
            img, dep, fg = render_observation(means, quats, scales, op, torch.cat([wall_col, blob_col]).clamp(0, 1),
                                              dyn, w2c, K, width, height, backend="cpu")
            w2cs.append(w2c)
            imgs.append(img)
            depths.append(dep)
            fgs.append(fg)
    w2c = torch.stack(w2cs)
    # tracks: 1500 wall points and 500 blob points, projected into every frame
    pw, pb = wall[:1500], blob[:500]
    xy = []
    for f in range(frames):
        pts = torch.cat([pw, quat_apply(rot[f].expand(len(pb), 4), pb) + off[f]])
        uv, _ = project(K, w2c[f], pts)
        xy.append(uv)
    tracks = torch.stack(xy, 1)
    vis = (tracks[..., 0] > 0) & (tracks[..., 0] < width) & (tracks[..., 1] > 0) & (tracks[..., 1] < height)
    idx = torch.arange(frames)
    data = TrainingData(images=torch.stack(imgs), K=K.expand(frames, 3, 3).clone(), w2c=w2c, times=times,
                        train_idx=idx[~val], val_idx=idx[val], depth=torch.stack(depths), fg=torch.stack(fgs),
                        tracks_xy=tracks, tracks_vis=vis, extent=4.0, frame_numbers=idx + 1, fps=24.0).validate()

    # nodes: ~87 % spread over the wall (static), the rest in the blob following its motion
    n_blob = max(4, nodes * 13 // 100)
    n_wall = nodes - n_blob
    cw = wall[torch.randperm(nw, generator=g)[:n_wall]]
    cb = blob[torch.randperm(nb, generator=g)[:n_blob]]
    centers = torch.cat([cw, cb])
    n_keys = max(4, min(24, int((~val).sum()) // 4))
    kt = torch.linspace(0, 1, n_keys)
    koff, krot = blob_motion(kt)
    pos = centers[:, None, :].expand(-1, n_keys, 3).clone()
    pos[n_wall:] = quat_apply(krot[None].expand(n_blob, n_keys, 4), cb[:, None].expand(-1, n_keys, 3)) + koff[None]
    rk = torch.zeros(len(centers), n_keys, 4)
    rk[..., 0] = 1
    rk[n_wall:] = krot[None]
    graph = node_graph(centers, 8)[0]
    p_dyn = torch.cat([torch.zeros(n_wall), torch.ones(n_blob)])
    nodes_arr = B.NodeArrays(centers=centers.numpy(), radii=node_radii(centers).numpy(), key_times=kt.numpy(),
                             pos_keys=pos.numpy(), pos_tangents=catmull_rom_tangents(kt, pos).numpy(),
                             rot_keys=rk.numpy(), rot_tangents=catmull_rom_tangents(kt, rk).numpy(),
                             p_dyn=p_dyn.numpy(), graph_idx=graph.numpy().astype(np.int64))
    return data, nodes_arr


# ----------------------------------------------------------------------------------
# Timing (runs in the worker subprocess)
# ----------------------------------------------------------------------------------
def _wrap_backward(cls, name, timer):
    """Time ``cls.backward`` (an autograd.Function) into ``timer[name]``; returns an undo."""
    original = cls.__dict__["backward"]
    fn = original.__func__ if isinstance(original, staticmethod) else original

    def timed(ctx, *grads):
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            return fn(ctx, *grads)
        finally:
            timer.add(name, time.perf_counter() - w0, time.process_time() - c0)

    cls.backward = staticmethod(timed)
    return lambda: setattr(cls, "backward", original)


def _load_1m() -> float | None:
    try:
        with open("/proc/loadavg") as fh:
            return float(fh.read().split()[0])
    except (OSError, ValueError):
        return None


def measure(data, nodes, cfg_overrides: dict, steps: int, warmup: int, out_dir) -> dict:
    """Time ``steps`` training steps (after ``warmup``) of a Trainer on ``data``/``nodes``.

    Returns the row's numbers (see the module docstring for the columns).
    """
    import torch

    from ..raster import cpu as raster_cpu
    from ..train import fused
    from ..train.config import preset_config
    from ..train.phases import PhaseTimer
    from ..train.trainer import Trainer

    base = preset_config("preview", **cfg_overrides)
    # start inside the densification window, after the static warm-up; keep densify
    # events, rebinds and checkpoints out of the timed window (densify is timed once below)
    start = base.densify_from + 1
    end = start + warmup + steps
    # the main training step only: the shot-detail stage after it (engine/train/shot_detail.py)
    # would run at the end of each train() call below
    cfg = preset_config("preview", **{**cfg_overrides, "steps": end, "checkpoint_every": 0, "rebind_every": 0,
                                       "densify_every": end + 1, "densify_until": end + 1, "log_every": 10,
                                       "shot_detail": "off"})
    if cfg.device == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit("--device cuda: torch sees no CUDA device")
        data = data.to("cuda")
    t0 = time.perf_counter()
    trainer = Trainer(data, nodes, cfg, out_dir)
    setup_s = time.perf_counter() - t0
    trainer.step = start
    gaussians, n_nodes = trainer.model.num_gaussians, trainer.model.num_nodes
    timer = PhaseTimer()
    undo = [_wrap_backward(raster_cpu.ProjectCPU, "bwd_raster", timer),
            _wrap_backward(raster_cpu.RasterizeCPU, "bwd_raster", timer),
            _wrap_backward(fused._FusedDeform, "bwd_deform", timer)]
    try:
        trainer.phases = timer
        cfg.steps = start + warmup
        trainer.train()
        timer.reset()
        cfg.steps = end
        w0, c0 = time.perf_counter(), time.process_time()
        trainer.train()
        if trainer.model.means.is_cuda:
            torch.cuda.synchronize()  # count the queued kernels in the timed window
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    finally:
        for u in undo:
            u()
        trainer.phases = None
    # one densification event on the trained state (what every densify_every-th step adds)
    w1 = time.perf_counter()
    trainer._densify()
    densify_s = time.perf_counter() - w1

    per = lambda s: round(1000.0 * s / steps, 2)  # noqa: E731
    ph = dict(timer.wall)
    top = ("deform", "sh", "raster_fwd", "losses", "backward", "optimizer", "densify_stats")
    ph["bwd_torch"] = ph.get("backward", 0.0) - ph.get("bwd_raster", 0.0) - ph.get("bwd_deform", 0.0)
    ph["other"] = wall - sum(ph.get(k, 0.0) for k in top)
    row = {"width": data.width, "height": data.height, "gaussians": gaussians, "nodes": n_nodes,
           "frames": data.num_frames, "steps": steps, "its_per_s": round(steps / wall, 3),
           "ms_step": per(wall), "cpu_ms_step": per(cpu)}
    row.update({k: per(ph.get(k, 0.0)) for k in PHASES})
    row.update({f"cpu_{k}": per(timer.cpu.get(k, 0.0)) for k in top})
    row["densify_ms"] = round(1000.0 * densify_s, 1)
    row["its_per_s_amortised"] = round(1.0 / (wall / steps + densify_s / base.densify_every), 3)
    row["setup_s"] = round(setup_s, 2)
    row["threads"] = torch.get_num_threads()
    row["device"] = str(trainer.model.means.device)
    row["backend"] = cfg.backend
    return row


def _worker(spec: dict) -> dict:
    import torch

    if spec.get("threads"):
        torch.set_num_threads(int(spec["threads"]))
    t0 = time.perf_counter()
    overrides = {"seed": spec["seed"], "width": spec["width"], "device": spec.get("device") or "cpu"}
    if spec.get("clip"):
        from .. import pipeline
        from ..train.config import preset_config

        cfg = preset_config("preview", **overrides)
        clip = pipeline.open_clip(spec["clip"])
        prep = pipeline.prepare(clip, cfg, cache_dir=Path(spec["work"]) / "cache" / Path(spec["clip"]).name)
        nodes = pipeline.initial_nodes(prep, cfg)
        data = pipeline.training_data(prep, torch.device("cpu"))  # the Trainer moves it to cfg.device
        scene = str(spec["clip"])
    else:
        data, nodes = synthetic_scene(spec["width"], spec["frames"], spec["nodes"], spec["seed"])
        # enough back-projected samples per keyframe for ~``gaussians`` at init (budget = the same)
        # (the static / dynamic split seeds a fifth of them on the moving blob in every frame)
        keyframes = 8
        dynamic = spec["gaussians"] // 5
        overrides.update(num_nodes=nodes.count, init_keyframes=keyframes, dynamic_gaussians=dynamic,
                         gaussians_per_frame=max(1, (spec["gaussians"] - dynamic) // keyframes),
                         max_gaussians=spec["gaussians"])
        scene = "synthetic"
    scene_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        row = measure(data, nodes, overrides, spec["steps"], spec["warmup"], Path(tmp) / "run")
    return {"scene": scene, **row, "scene_s": round(scene_s, 2), "peak_rss_mb": round(peak_rss_mb(), 1),
            "load_1m": _load_1m(), **machine_description()}


def paired_summary(rows: list[dict]) -> dict:
    """The summary row of a ``--baseline`` run: medians of both trees' ``its_per_s`` and of
    the per-pair step-time ratio (this tree / baseline), from ``rows`` tagged ``tree`` and
    ``pair``. Pairs are compared, not the pooled rows, because a shared machine's speed drifts
    between minutes by more than most changes are worth."""
    from statistics import median

    head = {r["pair"]: r for r in rows if r.get("tree") == "head"}
    base = {r["pair"]: r for r in rows if r.get("tree") == "baseline"}
    pairs = sorted(set(head) & set(base))
    if not pairs:
        raise ValueError("no complete pair of rows to summarise")
    ratios = [head[i]["ms_step"] / base[i]["ms_step"] for i in pairs]
    return {"summary": "paired", "pairs": len(pairs),
            "its_per_s_median": round(median(head[i]["its_per_s"] for i in pairs), 3),
            "baseline_its_per_s_median": round(median(base[i]["its_per_s"] for i in pairs), 3),
            "step_ratio_median": round(median(ratios), 4), "step_ratio_min": round(min(ratios), 4),
            "step_ratio_max": round(max(ratios), 4)}


def _baseline_tree(path: str) -> Path:
    tree = Path(path).expanduser().resolve()
    if not (tree / "engine" / "bench" / "train.py").is_file():
        raise SystemExit(f"--baseline {path}: no engine/bench/train.py there; give a tree of this project, e.g. "
                         f"`git worktree add {path} REV` or `mkdir {path} && git archive REV engine | tar -x -C {path}`")
    return tree


def run(args) -> list[dict]:
    spec = {"clip": args.clip, "width": args.width, "gaussians": args.gaussians, "nodes": args.nodes,
            "frames": args.frames, "steps": args.steps, "warmup": args.warmup, "threads": args.threads,
            "seed": args.seed, "device": args.device}
    if args.worker:  # the subprocess side
        return [_worker(json.loads(args.worker))]
    work = Path(args.work) if args.work else Path(tempfile.gettempdir()) / "motion_splats_bench" / "train"
    spec["work"] = str(work)
    repo = Path(__file__).resolve().parents[2]
    trees = [("head", repo)]
    if getattr(args, "baseline", None):
        trees.append(("baseline", _baseline_tree(args.baseline)))
    env = dict(os.environ)
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # what `python -m engine` sets (engine/__main__.py)
    rows = []
    for i in range(args.repeats):
        # alternate which tree goes first, so a drift within a pair does not favour one
        for name, tree in (trees if i % 2 == 0 else trees[::-1]):
            # the same interpreter; `-m` imports `engine` from the tree it runs in
            cmd = [sys.executable, "-m", "engine.bench", "train", "--json", "--worker", json.dumps(spec)]
            proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"train bench worker failed in {tree} ({proc.returncode}): {proc.stderr[-3000:]}")
            line = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")][-1]
            row = json.loads(line)
            if len(trees) > 1:
                row = {"tree": name, "pair": i + 1, **row}
            shown = ("tree",) * (len(trees) > 1) + ("its_per_s", "ms_step", "cpu_ms_step", "load_1m")
            print(json.dumps({"progress": {k: row.get(k) for k in shown}}), file=sys.stderr, flush=True)
            rows.append(row)
    if len(trees) > 1:
        rows.append(paired_summary(rows))
    return rows
