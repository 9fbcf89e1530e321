"""Build time of a large result into Blender: node Empties + F-curves, rig, Gaussians.

Examples::

    python -m engine.bench build                     # 2000 nodes x 60 keys, 200k Gaussians
    python -m engine.bench build --preview POINTS,ELLIPSOIDS --eval-frame --json
    python -m engine.bench build --nodes 20 --frames 5 --gaussians 500    # a quick check

A synthetic bundle (random node centres and smooth random trajectories, one key per
frame, Catmull-Rom tangents, K=4 nearest-node RBF binding, random Gaussians; written with
``engine.bundle``) is built into a fresh scene by ``tools/bpy_scene.py build``, a child
process with this interpreter (the venv's ``bpy`` module; ``engine/`` never imports bpy).
One row per preview mode with the add-on builder's own breakdown (seconds):

``load``        read and validate the bundle (PLY, npz, scene.json)
``empties``     one Empty per node
``fcurves``     location + quaternion F-curves, FREE Bézier handles, bulk ``foreach_set``
``rig``         the Armature (one bone per node) and the Gaussian mesh with vertex groups
``attributes``  ``ms_*`` point attributes on the mesh
``preview``     the Geometry Nodes preview modifier and material
``camera``      the animated camera and Cycles settings
``total``       all of the above (issue #7 target: ≤ 20 s at 2k nodes × 60 keys, 200k
                Gaussians on 2 cores); ``wall_s`` adds the child's start-up and bpy import

``ELLIPSOIDS`` builds also carry two auxiliary rigged vertices per Gaussian (their
rotation in Cycles), so their mesh is three times larger. ``--eval-frame`` adds the
first depsgraph evaluation of a frame (armature deform + preview), which Blender does
lazily after the build and is not part of it.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import run_child

HELP = "time building 2k nodes x 60 keys + 200k Gaussians into Blender (Empties, F-curves, rig, preview)"

REPO = Path(__file__).resolve().parents[2]
TARGET_S = 20.0


def add_arguments(parser):
    parser.add_argument("--nodes", type=int, default=2000, help="node count (default 2000)")
    parser.add_argument("--frames", type=int, default=60, help="frames = keys per node (default 60)")
    parser.add_argument("--gaussians", type=int, default=200_000, help="Gaussian count (default 200000)")
    parser.add_argument("--preview", default="POINTS,ELLIPSOIDS", help="preview modes, one row each "
                                                                       "(default POINTS,ELLIPSOIDS)")
    parser.add_argument("--eval-frame", action="store_true", help="also time the first evaluation of a frame")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", help="folder for the synthetic bundle (default: a temporary folder)")


def _catmull_rom(times: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Catmull-Rom tangents of ``keys [N, K, C]`` over ``times [K]`` (one-sided at the ends)."""
    tan = np.empty_like(keys)
    tan[:, 1:-1] = (keys[:, 2:] - keys[:, :-2]) / (times[2:] - times[:-2])[None, :, None]
    tan[:, 0] = (keys[:, 1] - keys[:, 0]) / (times[1] - times[0])
    tan[:, -1] = (keys[:, -1] - keys[:, -2]) / (times[-1] - times[-2])
    return tan


def synthetic_bundle(path, nodes: int = 2000, frames: int = 60, gaussians: int = 200_000, seed: int = 0,
                     bind_k: int = 4) -> Path:
    """Write a synthetic trained bundle (numpy + ``engine.bundle`` writers only)."""
    from .. import bundle as B

    rng = np.random.default_rng(seed)
    n, k, g = int(nodes), max(2, int(frames)), int(gaussians)
    extent = 2.0
    centers = rng.uniform(-extent, extent, (n, 3))
    radii = np.full(n, 2 * extent / max(n, 1) ** (1 / 3))
    times = np.linspace(0.0, 1.0, k)
    # smooth motion: a few random sinusoids per node, small rotations about random axes
    amp = 0.1 * rng.standard_normal((n, 1, 3))
    phase = rng.uniform(0, 2 * np.pi, (n, 1, 3))
    pos = centers[:, None] + amp * np.sin(2 * np.pi * times[None, :, None] + phase)
    axis = rng.standard_normal((n, 1, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    ang = 0.3 * np.sin(2 * np.pi * times[None, :, None] + phase[..., :1])
    rot = np.concatenate([np.cos(ang / 2), axis * np.sin(ang / 2)], -1)
    # binding: each Gaussian near a random node; its K nearest nodes by brute force in chunks
    means = centers[rng.integers(0, n, g)] + 0.5 * radii[0] * rng.standard_normal((g, 3))
    from scipy.spatial import cKDTree

    kb = min(bind_k, n)
    dist, idx = cKDTree(centers).query(means, k=kb)
    dist, idx = dist.reshape(g, kb), idx.reshape(g, kb).astype(np.int64)
    w = np.exp(-dist ** 2 / (2 * radii[idx] ** 2)) + 1e-12
    w = (w / w.sum(1, keepdims=True)).astype(np.float32)
    node_arrays = B.NodeArrays(centers=centers, radii=radii, key_times=times, pos_keys=pos,
                               pos_tangents=_catmull_rom(times, pos), rot_keys=rot,
                               rot_tangents=_catmull_rom(times, rot), bind_idx=idx, bind_w=w)
    quats = rng.standard_normal((g, 4))
    gs = B.GaussianArrays(means=means, quats=quats / np.linalg.norm(quats, axis=1, keepdims=True),
                          log_scales=np.log(rng.uniform(0.2, 0.6, (g, 3)) * radii[0]),
                          opacity_logits=rng.normal(size=g), sh=rng.normal(size=(g, 1, 3)))
    cams = []
    for j, t in enumerate(times):
        a = 0.5 * t
        R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, [0.0, 0.0, 4 * extent]
        cams.append({"frame": j + 1, "w2c": w2c, "K": [[300.0, 0, 160.0], [0, 300.0, 120.0], [0, 0, 1]],
                     "width": 320, "height": 240, "time": float(t), "split": "train"})
    scene = B.new_scene(1, k, 24.0, cams, extent=extent, stats={"synthetic": True})
    return B.save_bundle(path, scene, node_arrays, gs)


def run_bpy(args: list[str]) -> tuple[dict, float, float]:
    """``python tools/bpy_scene.py ARGS`` in a child; returns (its JSON result, wall s, its peak RSS MiB)."""
    cmd = [sys.executable, str(REPO / "tools" / "bpy_scene.py"), *map(str, args)]
    out_text, err_text, code, wall, rss = run_child(cmd, REPO)
    lines = [ln for ln in out_text.splitlines() if ln.startswith("{")]
    if code != 0 or not lines:
        raise RuntimeError(f"tools/bpy_scene.py {args[0]} failed (exit {code}); it needs the bpy "
                           f"module in {sys.executable}. {err_text[-1500:]}")
    return json.loads(lines[-1]), wall, rss


def run(args) -> list[dict]:
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="ms_bench_build_"))
    bundle = work / f"synthetic_n{args.nodes}_k{args.frames}_g{args.gaussians}_s{args.seed}"
    t0 = time.perf_counter()
    if not (bundle / "scene.json").is_file():
        synthetic_bundle(bundle, args.nodes, args.frames, args.gaussians, args.seed)
    gen_s = time.perf_counter() - t0
    rows = []
    for preview in [p.strip().upper() for p in args.preview.split(",") if p.strip()]:
        cmd = ["build", bundle, "--preview", preview] + (["--eval-frame"] if args.eval_frame else [])
        res, wall, rss = run_bpy(cmd)
        tm = res["timings"]
        row = {"nodes": res["nodes"], "keys": res["keys"], "gaussians": res["gaussians"], "preview": preview}
        for part in ("load", "empties", "fcurves", "rig", "attributes", "preview", "camera", "total"):
            row[f"{part}_s"] = tm.get(part)
        row["target_s"] = TARGET_S
        row["within_target"] = bool(tm.get("total", 1e9) <= TARGET_S)
        if "eval_frame_s" in res:
            row["eval_frame_s"] = res["eval_frame_s"]
        row.update(wall_s=round(wall, 2), peak_rss_mb=None if rss is None else round(rss, 1),
                   generate_s=round(gen_s, 2), cores=os.cpu_count(), load_1m=round(os.getloadavg()[0], 2))
        print(json.dumps({"progress": row}), file=sys.stderr, flush=True)
        rows.append(row)
    return rows
