"""Node initialisation bench: MANI vs FPS / uniform voxels / tracklet clustering.

Default mode: a ``tools/synth_scene.py`` scene (generated fresh with ``--preset``, needs
bpy; or an existing folder with ``--scene DIR``) goes through the REAL front end:
``engine.pipeline.open_clip`` + ``prepare`` (frames at the clip's own width, weight-free
default priors on the train frames, GT cameras) and ``engine.nodes.initialise_nodes`` for
mani / fps / voxel / tracklet at one node budget (spline trajectories), plus mani with
``trajectory='static'``. Measured against the scene's ground truth (train ``left_*`` frames):

``dyn_frac``
    Fraction of nodes on a dynamic surface: the node centre projected with the GT camera
    of its source frame (the frame nearest its source time) lands on a GT-mask pixel.
    Nodes outside the image count as static.
``density_ratio``
    ``(dynamic nodes / dynamic share) / (static nodes / static share)``; the shares are
    GT-mask pixel fractions over all train frames (image area, not surface area).
``traj_err`` / ``traj_err_dyn``
    For every GT surface point (``gt/trajectories.npz``; ``_dyn``: the dynamic ones) and
    reference frame r ∈ {first, middle, last}: the K=4 nearest nodes at time t_r (by
    ``p_i(t_r)``) blend their displacement ``p_i(t) − p_i(t_r)`` with RBF weights
    ``exp(−d²/2ρ_i²)`` (ρ = node radius, normalised), added to the GT position at r, vs the
    GT trajectory; mean ‖·‖ over points, frames and r, in scene units (``*_abs``) and as a
    fraction of the scene extent (diagonal of the GT points' bounding box over all frames).
    ``zero_motion_dyn`` is the error of predicting no motion under the same protocol (same
    reference frames; the GT motion scale): a node set that does not move scores exactly it.

Diagnostics (generated scenes): ``--oracle-depth`` / ``--oracle-mask`` replace the depth /
dynamic prior with the scene's GT depth / mask (one input at a time shows which prior
limits the trajectories). ``--diagnose`` adds two GT-motion ceilings on the same MANI
nodes: ``gt-motion`` gives every node the GT motion of the surface at its source pixel
(GT depth there, nearest GT trajectory point) while keeping its position, i.e. the best a
trajectory initialiser can do with the node depths as placed; ``gt-motion@gt-depth`` also
slides the node along its source ray to the GT depth.

``--procedural`` keeps the older torch-only scene (static floor + wall, three moving boxes,
GT-mask-with-noise prior, tokens from object prototypes); there ``dyn_frac`` uses the
nearest GT point at the node's source time and ``traj_err`` the node's nearest GT point.

A last row times MANI on 100k random candidates (D=384) → 2k nodes (issue #5: ≤ 3 s on
2 cores), with the torch thread count, the 1-minute load average and ``cpu_s``, the
process's CPU seconds over all threads (on a shared machine wall time is inflated by other
jobs; ``cpu_s`` / threads is a lower bound of the idle wall time, ``cpu_s`` an upper one).
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

HELP = "node initialisation: MANI vs baselines vs ground truth (tools/synth_scene.py scene or --procedural)"


def add_arguments(parser) -> None:
    parser.add_argument("--budget", type=int, default=400)
    parser.add_argument("--scene", metavar="DIR", help="existing tools/synth_scene.py folder (default: generate)")
    parser.add_argument("--preset", choices=("tiny", "small"), default="small", help="preset to generate")
    parser.add_argument("--keep", metavar="DIR", help="generate into DIR and keep it (default: a temp folder)")
    parser.add_argument("--procedural", action="store_true", help="use the procedural torch scene instead")
    parser.add_argument("--frames", type=int, default=24, help="frames of the procedural scene")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--oracle-depth", action="store_true", help="use the scene's GT depth instead of the depth prior")
    parser.add_argument("--oracle-mask", action="store_true", help="use the scene's GT mask instead of the dynamic prior")
    parser.add_argument("--diagnose", action="store_true",
                        help="add rows: opt-in trajectory variants and GT-motion ceilings (generated scenes)")


def _quat_rot(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (F, 3, 3) about z from angles (F,)."""
    c, s = torch.cos(axis_angle), torch.sin(axis_angle)
    z, o = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


def make_scene(frames: int = 24, h: int = 192, w: int = 256, patch: int = 8, dim: int = 64, seed: int = 0):
    """Procedural dynamic scene; returns a dict of the engine inputs + GT."""
    from ..geometry.camera import look_at, project

    g = torch.Generator().manual_seed(seed)
    times = torch.linspace(0, 1, frames)
    pts, obj = [], []
    n_floor, n_wall = 60000, 40000
    pts.append(torch.stack([torch.rand(n_floor, generator=g) * 8 - 4, torch.rand(n_floor, generator=g) * 6 - 2,
                            torch.zeros(n_floor)], 1)); obj.append(torch.zeros(n_floor, dtype=torch.long))
    pts.append(torch.stack([torch.rand(n_wall, generator=g) * 8 - 4, torch.full((n_wall,), 4.0),
                            torch.rand(n_wall, generator=g) * 4], 1)); obj.append(torch.ones(n_wall, dtype=torch.long))
    traj = [pts[0].unsqueeze(1).expand(-1, frames, -1), pts[1].unsqueeze(1).expand(-1, frames, -1)]
    centres = torch.tensor([[-1.5, 0.5, 0.5], [1.0, 1.5, 0.6], [0.0, -0.5, 0.4]])
    for j in range(3):
        n_box = 8000
        u = torch.rand(n_box, 3, generator=g) * 2 - 1
        face = torch.randint(3, (n_box,), generator=g)
        u[torch.arange(n_box), face] = torch.sign(u[torch.arange(n_box), face])  # on the box surface
        local = u * torch.tensor([0.45, 0.3, 0.35])
        ang = 2.0 * math.sin(j + 1) * times * math.pi
        path = centres[j] + torch.stack([torch.sin(2 * math.pi * times + j), 0.6 * torch.cos(2 * math.pi * times * (j + 1) / 2),
                                         0.2 * torch.sin(4 * math.pi * times)], 1) * 0.8
        traj.append(torch.einsum("fab,nb->nfa", _quat_rot(ang), local) + path.unsqueeze(0))
        obj.append(torch.full((n_box,), 2 + j, dtype=torch.long))
    traj = torch.cat(traj)  # [M, F, 3]
    obj = torch.cat(obj)
    dynamic = obj >= 2
    eyes = torch.stack([6 * torch.sin(0.6 * times - 0.3), -6 * torch.cos(0.6 * times - 0.3), torch.full_like(times, 3.5)], 1)
    w2c = torch.stack([look_at(e.double(), torch.tensor([0.0, 1.0, 0.5], dtype=torch.float64)) for e in eyes]).float()
    K = torch.tensor([[200.0, 0, w / 2], [0, 200.0, h / 2], [0, 0, 1]]).expand(frames, 3, 3).clone()
    uv, z = project(K.unsqueeze(0), w2c.unsqueeze(0), traj)  # [M, F, 2], [M, F]
    col, row = uv[..., 0].floor().long(), uv[..., 1].floor().long()
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & (z > 0.1)
    pix = torch.where(inside, torch.arange(frames) * h * w + row * w + col, torch.zeros_like(col))
    zz = torch.where(inside, z, torch.full_like(z, float("inf")))
    depth = torch.full((frames * h * w,), float("inf")).scatter_reduce(0, pix.reshape(-1), zz.reshape(-1), "amin")
    win = torch.full((frames * h * w,), -1, dtype=torch.long)
    is_win = inside & (zz <= depth[pix] + 1e-6)
    ids = torch.arange(traj.shape[0]).unsqueeze(1).expand_as(pix)
    win[pix[is_win]] = ids[is_win]
    depth = torch.where(torch.isfinite(depth), depth, torch.zeros_like(depth)).reshape(frames, h, w)
    win = win.reshape(frames, h, w)
    dyn_mask = (win >= 0) & dynamic[win.clamp_min(0)]
    fg = (dyn_mask.float() * 0.8 + 0.1 + 0.1 * torch.randn(frames, h, w, generator=g)).clamp(0, 1)
    gh, gw = h // patch, w // patch
    yy, xx = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
    patch_centers = torch.stack([xx * patch + patch / 2, yy * patch + patch / 2], -1).float()
    pc = patch_centers.long()
    pwin = win[:, pc[..., 1], pc[..., 0]]  # [F, Gh, Gw]
    pobj = torch.where(pwin >= 0, obj[pwin.clamp_min(0)], torch.zeros_like(pwin))
    proto = torch.randn(5, dim, generator=g)
    drift = torch.randn(5, dim, generator=g)
    phase = (times * 2 * math.pi).view(frames, 1, 1, 1)
    is_dyn = (pobj >= 2).unsqueeze(-1).float()
    tokens = proto[pobj] + is_dyn * (torch.sin(phase) * drift[pobj] * 1.5) + 0.4 * torch.randn(frames, gh, gw, dim, generator=g)
    # Tracks: GT points visible in some frame; visible = z-buffer winner within tolerance.
    n_tracks = 3000
    pick = torch.randperm(traj.shape[0], generator=g)[:n_tracks]
    vis = inside[pick] & ((z[pick] - depth.reshape(-1)[pix[pick]]).abs() < 0.03)
    return dict(depth=depth, K=K, w2c=w2c, times=times, tokens=tokens, patch_centers=patch_centers, fg=fg,
                tracks_xy=uv[pick], tracks_vis=vis, gt_traj=traj, gt_dynamic=dynamic)


def evaluate(nodes, scene) -> dict:
    """Node-placement and trajectory metrics against the GT surface points."""
    from ..geometry.binding import knn_nodes
    from ..geometry.hermite import hermite_eval

    traj, dynamic, times = scene["gt_traj"], scene["gt_dynamic"], scene["times"]
    frame = (nodes.source_time.unsqueeze(1) - times.unsqueeze(0)).abs().argmin(1)
    gt_idx = torch.empty(nodes.num_nodes, dtype=torch.long)
    for f in torch.unique(frame).tolist():  # loop over frames
        sel = torch.nonzero(frame == f).squeeze(1)
        gt_idx[sel] = knn_nodes(nodes.centers[sel], traj[:, f], 1)[0][:, 0]
    node_dyn = dynamic[gt_idx]
    n_dyn, n_stat = int(node_dyn.sum()), int((~node_dyn).sum())
    density = (n_dyn / int(dynamic.sum())) / max(n_stat / int((~dynamic).sum()), 1e-12)
    pred = hermite_eval(nodes.key_times, nodes.pos_keys, nodes.pos_tangents, times)  # [N, F, 3]
    err = (pred - traj[gt_idx]).norm(dim=-1).mean(1)
    diag = float((traj[:, 0].max(0).values - traj[:, 0].min(0).values).norm())
    return {"nodes": nodes.num_nodes, "dyn_frac": n_dyn / nodes.num_nodes, "density_ratio": density,
            "traj_err": float(err.mean()) / diag, "traj_err_dyn": float(err[node_dyn].mean()) / diag if n_dyn else float("nan")}


#: (initialiser, trajectory init) rows, in print order.
VARIANTS = (("mani", "spline"), ("mani", "static"), ("fps", "spline"), ("voxel", "spline"), ("tracklet", "spline"))


def _load_avg() -> float:
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return float("nan")


def speed_row(seed: int = 0) -> dict:
    """MANI on 100k random candidates (D=384) → 2k nodes."""
    from ..nodes import ManiConfig, mani_compress
    from .common import machine_description

    g = torch.Generator().manual_seed(seed)
    n, d = 100_000, 384
    pos = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 3.0, 2.0])
    fg = (pos[:, 0] < 0.8).float()
    tok = torch.randn(8, d, generator=g)[(pos[:, 1] * 2).long().clamp(0, 7)] + 0.3 * torch.randn(n, d, generator=g)
    load = _load_avg()
    c0, t0 = time.process_time(), time.perf_counter()
    res = mani_compress(pos, tok, fg, ManiConfig(budget=2000))
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0  # this process's CPU seconds (all threads): robust to a shared machine
    return {"scene": "speed: 100k random candidates, D=384", "init": "mani", "trajectory": "-",
            "nodes": int(res.positions.shape[0]), "iterations": res.iterations, "wall_s": round(wall, 3),
            "cpu_s": round(cpu, 3),
            "threads": torch.get_num_threads(), "load_avg_1m": load, **machine_description()}


# ----------------------------------------------------------------------------------------
# generated scene (tools/synth_scene.py) through the real front end


def scene_gt(scene_dir, prep) -> dict:
    """GT for the prepared train frames: mask / K / w2c per prepared frame, trajectories."""
    import cv2

    from .priors import load_scene

    _, _, gt = load_scene(scene_dir)
    order = prep.priors.train_order
    n = len(order)
    if len(gt.w2c) != n:
        raise RuntimeError(f"prepared clip has {n} train frames, GT {len(gt.w2c)}")
    h, w = prep.frames.shape[1:3]
    mask = np.stack([cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0 for m in gt.mask])
    depth = np.stack([cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST) for d in gt.depth])
    depth = np.where(np.isfinite(depth) & (depth > 0) & (depth < 1e6), depth, 0).astype(np.float32)
    info = gt.info
    traj = np.load(Path(scene_dir) / "gt" / "trajectories.npz", allow_pickle=False)
    dyn = traj["is_dynamic"].astype(bool)
    return {"mask": mask, "depth": depth, "K": prep.K[order], "w2c": prep.w2c[order], "times": prep.times[order],
            "points": gt.points.astype(np.float32), "dynamic": dyn, "info": info}


def _rbf_deform_error(nodes, points: np.ndarray, times: np.ndarray, k: int = 4) -> np.ndarray:
    """Mean over frames and reference frames of the node-predicted vs GT trajectory error.

    Each GT point at a reference frame ``r`` binds to its ``k`` nearest nodes there (RBF
    weights of the node radii) and is carried to every frame ``t`` by their motion
    ``x(t) = Σ_i w_i [R_i(t) R_i(r)ᵀ (x(r) − p_i(r)) + p_i(t)]``: the nodes' turn counts, as
    it does in the model (without rotation keys, or with identity ones, this is the
    blended displacement ``x(r) + Σ_i w_i (p_i(t) − p_i(r))``).

    nodes : key_times (K,), pos_keys/pos_tangents (N, K, 3), radii (N,), optional
    rot_keys/rot_tangents (N, K, 4). points : (M, F, 3) GT. Returns (M,) errors in scene units.
    """
    from ..geometry.binding import knn_nodes
    from ..geometry.hermite import hermite_eval, hermite_eval_quat
    from ..geometry.quaternion import quat_to_matrix

    pts = torch.as_tensor(points).float()
    f = pts.shape[1]
    t = torch.as_tensor(times).float()
    pred_nodes = hermite_eval(nodes.key_times, nodes.pos_keys, nodes.pos_tangents, t)  # [N, F, 3]
    rot_keys = getattr(nodes, "rot_keys", None)
    rot = None
    if rot_keys is not None:
        rot = quat_to_matrix(hermite_eval_quat(nodes.key_times, rot_keys, nodes.rot_tangents, t))  # [N, F, 3, 3]
    rho = nodes.radii.float().clamp_min(1e-6)
    errs = []
    for r in sorted({0, f // 2, f - 1}):  # reference frames
        kk = min(k, pred_nodes.shape[0])
        idx, d2 = knn_nodes(pts[:, r], pred_nodes[:, r], kk)  # [M, kk] node ids per point
        w = torch.exp(-d2 / (2 * rho[idx] ** 2))
        w = torch.where(w.sum(1, keepdim=True) > 1e-12, w, torch.ones_like(w))  # far points: plain mean
        w = w / w.sum(1, keepdim=True)
        off = pts[:, None, r] - pred_nodes[idx][:, :, r]  # [M, kk, 3] offset from each node at r
        if rot is not None:  # R_i(t) R_i(r)^T off
            rel = rot[idx] @ rot[idx][:, :, r:r + 1].transpose(-1, -2)  # [M, kk, F, 3, 3]
            moved = (rel @ off[:, :, None, :, None])[..., 0]  # [M, kk, F, 3]
        else:
            moved = off.unsqueeze(2)
        pred = (w[..., None, None] * (moved + pred_nodes[idx])).sum(1)  # [M, F, 3]
        errs.append((pred - pts).norm(dim=-1).mean(1))
    return torch.stack(errs).mean(0).numpy()


def _zero_motion_error(points: np.ndarray) -> np.ndarray:
    """The error of predicting no motion under :func:`_rbf_deform_error`'s protocol.

    points : (M, F, 3) GT. Returns (M,): ``mean_t ‖p(t) − p(t_r)‖`` averaged over the same
    reference frames r, so a node set that does not move scores exactly this.
    """
    f = points.shape[1]
    refs = sorted({0, f // 2, f - 1})
    return np.mean([np.linalg.norm(points - points[:, r:r + 1], axis=-1).mean(1) for r in refs], axis=0)


def evaluate_gt(nodes, gt: dict) -> dict:
    """Node-placement and trajectory metrics of a NodeSet against a generated scene's GT."""
    centers = nodes.centers.double().numpy()
    times = gt["times"]
    frame = np.abs(nodes.source_time.double().numpy()[:, None] - times[None]).argmin(1)
    K, w2c, mask = gt["K"][frame], gt["w2c"][frame], gt["mask"]
    xc = np.einsum("nij,nj->ni", w2c[:, :3, :3], centers) + w2c[:, :3, 3]
    uvw = np.einsum("nij,nj->ni", K, xc)
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    _, h, w = mask.shape
    inside = (xc[:, 2] > 0) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    col = np.clip(np.nan_to_num(u), 0, w - 1).astype(int)
    row = np.clip(np.nan_to_num(v), 0, h - 1).astype(int)
    node_dyn = inside & mask[frame, row, col]
    n = len(centers)
    n_dyn = int(node_dyn.sum())
    share = float(mask.mean())
    density = (n_dyn / share) / max((n - n_dyn) / (1 - share), 1e-12)
    pts, dyn = gt["points"], gt["dynamic"]
    err = _rbf_deform_error(nodes, pts, times)
    ext = float(np.linalg.norm(pts.reshape(-1, 3).max(0) - pts.reshape(-1, 3).min(0)))
    zero = _zero_motion_error(pts[dyn]).mean() if dyn.any() else float("nan")
    return {"nodes": n, "dyn_frac": n_dyn / n, "dyn_share_gt": share, "density_ratio": density,
            "off_image": int((~inside).sum()),
            "traj_err_dyn": float(err[dyn].mean()) / ext, "traj_err": float(err.mean()) / ext,
            "traj_err_dyn_abs": float(err[dyn].mean()), "traj_err_abs": float(err.mean()),
            "zero_motion_dyn": float(zero) / ext, "extent": ext}


def gt_motion_nodes(nodes, gt: dict, at_gt_depth: bool = False):
    """The same nodes with GT-derived trajectories (a ceiling for trajectory initialisation).

    Each node's centre is projected into its source frame (GT camera); the GT depth at that
    pixel gives the surface point it stands for, and the nearest GT trajectory point to it
    (at that frame) gives its motion. The node keeps its position (``at_gt_depth=False``)
    or slides along its source ray to the GT depth (pixel unchanged). Nodes whose pixel is
    off-image or has no GT depth stay static.
    """
    import dataclasses

    from ..geometry.binding import knn_nodes
    from ..geometry.camera import project, unproject
    from ..geometry.hermite import catmull_rom_tangents, hermite_fit

    times = torch.as_tensor(gt["times"]).float()
    K, w2c = torch.as_tensor(gt["K"]).float(), torch.as_tensor(gt["w2c"]).float()
    pts = torch.as_tensor(gt["points"]).float()
    depth = torch.as_tensor(gt["depth"]).float()
    c = nodes.centers.float()
    sf = (nodes.source_time.float()[:, None] - times[None]).abs().argmin(1)
    uv, z = project(K[sf], w2c[sf], c)
    h, w = depth.shape[1:]
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    col = uv[:, 0].nan_to_num(0).floor().long().clamp(0, w - 1)
    row = uv[:, 1].nan_to_num(0).floor().long().clamp(0, h - 1)
    zt = depth[sf, row, col]
    ok = inside & (zt > 0)
    surf = unproject(K[sf], w2c[sf], uv.nan_to_num(0), torch.where(ok, zt, torch.ones_like(zt)))
    gi = torch.zeros(len(c), dtype=torch.long)
    for f in torch.unique(sf).tolist():  # loop over frames
        sel = torch.nonzero(sf == f).squeeze(1)
        gi[sel] = knn_nodes(surf[sel], pts[:, f], 1)[0][:, 0]
    disp = pts[gi] - pts[gi, sf].unsqueeze(1)  # [N, F, 3]
    base = torch.where(ok[:, None], surf, c) if at_gt_depth else c
    path = base.unsqueeze(1) + disp * ok[:, None, None]
    keys = hermite_fit(nodes.key_times.float(), times, path)
    return dataclasses.replace(nodes, centers=base, pos_keys=keys,
                               pos_tangents=catmull_rom_tangents(nodes.key_times.float(), keys))


def run_generated(args) -> list[dict]:
    from .. import pipeline
    from ..nodes import ManiConfig, NodeInitConfig, initialise_nodes
    from ..train.config import TrainConfig
    from .priors import generate

    tmp = None
    if args.scene:
        scene_dir = Path(args.scene)
        label = scene_dir.name
    else:
        if args.keep:
            out = Path(args.keep)
        else:
            tmp = tempfile.TemporaryDirectory(prefix="nodes_bench_")
            out = Path(tmp.name) / args.preset
        t0 = time.perf_counter()
        scene_dir = generate(out, args.preset, None, args.seed)
        label = f"{args.preset} (generated, seed {args.seed}, {time.perf_counter() - t0:.0f} s)"
    try:
        clip = pipeline.open_clip(scene_dir, solve=False)
        cfg = TrainConfig(width=clip.width, seed=args.seed)
        t0 = time.perf_counter()
        prep = pipeline.prepare(clip, cfg)
        prep_s = time.perf_counter() - t0
        gt = scene_gt(scene_dir, prep)
        order = prep.priors.train_order
        n_train = len(order)
        pr, tr = prep.priors, prep.priors.tracks
        inputs = dict(depth=pr.depth[order], K=prep.K[order], w2c=prep.w2c[order], times=prep.times[order],
                      tokens=pr.tokens.tokens, patch_centers=pr.tokens.patch_centers, fg=pr.dynamic[order],
                      tracks_xy=tr.xy[:, order], tracks_vis=tr.visible[:, order],
                      tracks_depth=None if tr.depth is None else tr.depth[:, order])
        oracle = []
        if getattr(args, "oracle_depth", False):
            inputs["depth"] = gt["depth"]
            oracle.append("GT depth")
        if getattr(args, "oracle_mask", False):
            inputs["fg"] = gt["mask"].astype(np.float32)
            oracle.append("GT mask")
        if oracle:
            label = f"{label} ({' + '.join(oracle)})"
        num_keys = cfg.num_keys or max(4, min(24, n_train // 4))  # as pipeline.initial_nodes
        res = f"{prep.frames.shape[2]}x{prep.frames.shape[1]}x{n_train}f"
        rows = []
        for method, traj in VARIANTS:
            icfg = NodeInitConfig(method=method, trajectory=traj, mani=ManiConfig(budget=args.budget, seed=args.seed),
                                  num_keys=num_keys, num_keyframes=min(12, n_train), seed=args.seed)
            t0 = time.perf_counter()
            nodes = initialise_nodes(**inputs, config=icfg)
            wall = time.perf_counter() - t0
            rows.append({"scene": label, "res": res, "init": method, "trajectory": traj, **evaluate_gt(nodes, gt),
                         "wall_s": round(wall, 3), "prepare_s": round(prep_s, 2)})
            if method == "mani" and traj == "spline":
                mani_nodes = nodes
        if getattr(args, "diagnose", False):
            for name, at_depth in (("gt-motion", False), ("gt-motion@gt-depth", True)):
                rows.append({"scene": label, "res": res, "init": "mani", "trajectory": name,
                             **evaluate_gt(gt_motion_nodes(mani_nodes, gt, at_depth), gt),
                             "wall_s": float("nan"), "prepare_s": round(prep_s, 2)})
        return rows
    finally:
        if tmp is not None:
            tmp.cleanup()


def run_procedural(args) -> list[dict]:
    from ..nodes import ManiConfig, NodeInitConfig, initialise_nodes

    torch.manual_seed(args.seed)
    scene = make_scene(frames=args.frames, seed=args.seed)
    inputs = {k: scene[k] for k in ("depth", "K", "w2c", "times", "tokens", "patch_centers", "fg",
                                    "tracks_xy", "tracks_vis")}
    rows = []
    label = "procedural torch scene"
    for method, traj in VARIANTS:
        cfg = NodeInitConfig(method=method, trajectory=traj, mani=ManiConfig(budget=args.budget, seed=args.seed),
                             seed=args.seed)
        t0 = time.perf_counter()
        nodes = initialise_nodes(**inputs, config=cfg)
        wall = time.perf_counter() - t0
        rows.append({"scene": label, "init": method, "trajectory": traj, **evaluate(nodes, scene),
                     "wall_s": round(wall, 3)})
    return rows


def run(args) -> list[dict]:
    rows = run_procedural(args) if args.procedural else run_generated(args)
    if not args.skip_speed:
        rows.append(speed_row(args.seed))
    return rows
