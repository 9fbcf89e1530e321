"""Node initialisation bench: MANI vs FPS / uniform voxels / tracklet clustering.

Scene: a PROCEDURAL SYNTHETIC scene built in torch (tools/synth_scene.py is not wired in
yet): a static floor + back wall and three moving, rotating boxes, sampled densely as
surface points with ground-truth trajectories, seen by an orbiting camera. Depth and the
dynamic mask are z-buffered point splats; tokens are per-object prototypes + noise, with
the moving objects' tokens drifting over time; the foreground prior is the GT mask with
noise; tracks are projected GT points with z-buffer visibility.

Per initialiser at one node budget it prints: ``dyn_frac`` (nodes whose nearest GT point
at their source time is dynamic), ``density_ratio`` (dynamic nodes per dynamic surface
point ÷ static nodes per static surface point), ``traj_err`` (mean over nodes and frames of
‖p_i(t) − x_gt(t)‖ for the node's nearest GT point, as a fraction of the scene diagonal;
also for dynamic nodes only) and the wall time. A last row times MANI on 100k random
candidates (D=384) → 2k nodes.
"""

from __future__ import annotations

import math
import time

import torch

HELP = "node initialisation: MANI vs baselines on a procedural synthetic scene"


def add_arguments(parser) -> None:
    parser.add_argument("--budget", type=int, default=400)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-speed", action="store_true")


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


def run(args) -> list[dict]:
    from ..nodes import ManiConfig, NodeInitConfig, initialise_nodes, mani_compress
    from .common import machine_description

    torch.manual_seed(args.seed)
    scene = make_scene(frames=args.frames, seed=args.seed)
    inputs = {k: scene[k] for k in ("depth", "K", "w2c", "times", "tokens", "patch_centers", "fg",
                                    "tracks_xy", "tracks_vis")}
    rows = []
    label = "procedural synthetic scene (not tools/synth_scene.py)"
    for method, traj in (("mani", "spline"), ("mani", "static"), ("fps", "spline"), ("voxel", "spline"),
                         ("tracklet", "spline")):
        cfg = NodeInitConfig(method=method, trajectory=traj, mani=ManiConfig(budget=args.budget, seed=args.seed),
                             seed=args.seed)
        t0 = time.perf_counter()
        nodes = initialise_nodes(**inputs, config=cfg)
        wall = time.perf_counter() - t0
        rows.append({"scene": label, "init": method, "trajectory": traj, **evaluate(nodes, scene),
                     "wall_s": round(wall, 3)})
    if not args.skip_speed:
        g = torch.Generator().manual_seed(args.seed)
        n, d = 100_000, 384
        pos = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 3.0, 2.0])
        fg = (pos[:, 0] < 0.8).float()
        tok = torch.randn(8, d, generator=g)[(pos[:, 1] * 2).long().clamp(0, 7)] + 0.3 * torch.randn(n, d, generator=g)
        t0 = time.perf_counter()
        res = mani_compress(pos, tok, fg, ManiConfig(budget=2000))
        wall = time.perf_counter() - t0
        rows.append({"scene": "speed: 100k random candidates, D=384", "init": "mani", "trajectory": "-",
                     "nodes": int(res.positions.shape[0]), "iterations": res.iterations,
                     "wall_s": round(wall, 3), "threads": torch.get_num_threads(), **machine_description()})
    return rows
