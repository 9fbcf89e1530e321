"""Building the model before training: nodes in canonical space, Gaussians seeded from the
frames and mapped into it, and the static / dynamic split (``engine/train/split.py``).

``build_model(data, nodes, cfg, gen)`` is the entry point. With ``cfg.split`` the model
has static nodes (rest keys, frozen during training) carrying the static Gaussians,
seeded from the static pixels of ``cfg.init_keyframes`` frames, and dynamic nodes
carrying dynamic Gaussians seeded densely from the moving pixels of every training frame
(:func:`dynamic_gaussians`) -- so each moving object is seen at every time, not at
eight keyframes.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from .. import bundle as B
from ..errors import InputError
from ..geometry.binding import bind_gaussians
from ..geometry.camera import project, unproject
from ..geometry.dualquat import dq_apply_points, dq_blend, dq_inverse, node_transforms_dq
from ..geometry.quaternion import quat_conj, quat_identity, quat_mul, quat_normalize
from .config import TrainConfig
from .data import TrainingData
from .lifespan import data_lifespan, lifespan_seed_count
from .model import DynamicScene


def invert_at_time(model_like, points: torch.Tensor, t: float, k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Canonical points ``[P, 3]`` of world ``points [P, 3]`` observed at time ``t``, and the
    binding they were inverted through ``(idx [P, k], w [P, k])``: each point's ``k`` nearest
    nodes *at time t* (indices into ``model_like``'s nodes), their transforms blended and
    inverted. Deforming the canonical points with that binding gives ``points`` back at ``t``."""
    with torch.no_grad():
        pos, rot = model_like.node_state(t)
        idx, w = bind_gaussians(points, pos, model_like.node_radii(), k)
        dq = dq_blend(node_transforms_dq(model_like.node_centers, pos, rot), idx, w)
        # the inverse of a unit dual quaternion is its conjugate (both parts)
        return dq_apply_points(dq_inverse(dq), points), idx, w


def to_canonical(model_like, points: torch.Tensor, t: float, k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Invert the node deformation at time ``t`` for world points observed at ``t``.

    Binds ``points [P, 3]`` to the nodes' positions *at time t*, blends the node
    transforms and applies the inverse rigid transform (:func:`invert_at_time`). Returns
    canonical points ``[P, 3]`` and their binding ``(idx, w)`` in canonical space. Exact when
    the bound nodes move rigidly together; a good initial guess otherwise.
    """
    canon = invert_at_time(model_like, points, t, k)[0]
    with torch.no_grad():
        idx_c, w_c = bind_gaussians(canon, model_like.node_centers, model_like.node_radii(), k)
    return canon, idx_c, w_c


def _back_project(data: TrainingData, f: int, py: torch.Tensor, px: torch.Tensor, footprint_px: float):
    """World points, colours, isotropic scales and times of pixels ``(py, px) [P]`` of frame
    ``f`` (pixels without depth dropped); a Gaussian covers ~``footprint_px`` pixels."""
    z = data.depth[f][py, px]
    ok = z > 0
    py, px, z = py[ok], px[ok], z[ok]
    uv = torch.stack([px.to(z.dtype) + 0.5, py.to(z.dtype) + 0.5], -1)
    x = unproject(data.K[f], data.w2c[f], uv, z)
    scale = (0.5 * footprint_px * z / data.K[f, 0, 0]).unsqueeze(-1).expand(-1, 3)
    return x, data.images[f, py, px], scale, torch.full_like(z, float(data.times[f]))


def initial_gaussians(data: TrainingData, cfg: TrainConfig, gen: torch.Generator, static_only: bool = False):
    """Back-project pixels of ``cfg.init_keyframes`` training frames (depth + colour).

    With ``static_only`` pixels the dynamic prior marks as moving (``>= cfg.dynamic_threshold``)
    are skipped: a moving object sampled at a few keyframes and left undeformed is a row
    of frozen copies of it (:func:`dynamic_gaussians` seeds moving content instead).

    Returns world positions ``[G, 3]``, colours ``[G, 3]``, isotropic scales ``[G, 3]``,
    and the engine time each point was observed at ``[G]``.
    """
    if data.depth is None:
        raise InputError("training needs a depth prior to place the initial Gaussians", None,
                         "compute priors first (python -m engine prepare) or supply precomputed depth")
    train = data.train_idx
    n_key = min(cfg.init_keyframes, len(train))
    pick = train[torch.linspace(0, len(train) - 1, n_key).round().long()]
    h, w = data.height, data.width
    per = cfg.gaussians_per_frame
    footprint = math.sqrt(h * w / per)
    out = []
    for f in pick.tolist():  # a handful of keyframes; per-pixel work is vectorised
        flat = torch.randint(0, h * w, (per,), generator=gen, device="cpu").to(data.depth.device)
        py, px = flat // w, flat % w
        if static_only and data.fg is not None:
            still = data.fg[f][py, px] < cfg.dynamic_threshold
            py, px = py[still], px[still]
        out.append(_back_project(data, f, py, px, footprint))
    return tuple(torch.cat(parts) for parts in zip(*out))


def dynamic_gaussians(data: TrainingData, cfg: TrainConfig, gen: torch.Generator, distinct: bool = False):
    """Seed ``cfg.dynamic_gaussians`` Gaussians on the moving pixels of *every* training frame.

    Each frame gets a share proportional to its moving area (so a small object is not
    oversampled), drawn uniformly among its pixels with the dynamic prior at least
    ``cfg.dynamic_threshold``: independently, or with ``distinct`` each pixel once until every
    one has a Gaussian (:func:`distinct_pixels`; for seeds shown around their own frame only).
    Their footprint matches the density: ~``sqrt(area / n)`` pixels. Returns ``(world [D, 3],
    colours [D, 3], scales [D, 3], times [D])``; empty without a prior or moving pixels.
    """
    dev = data.images.device
    empty = (torch.zeros(0, 3, device=dev),) * 3 + (torch.zeros(0, device=dev),)
    if data.fg is None or cfg.dynamic_gaussians <= 0 or data.depth is None:
        return empty
    train = data.train_idx
    moving = data.fg[train] >= cfg.dynamic_threshold  # [T, H, W]
    area = moving.flatten(1).sum(1).to(torch.float32)  # [T]
    total = float(area.sum())
    if total < 1:
        return empty
    share = torch.floor(area / total * cfg.dynamic_gaussians).long().tolist()
    out = []
    for f, n_f, m_f in zip(train.tolist(), share, moving):  # frames; pixels vectorised
        if n_f <= 0:
            continue
        ys, xs = torch.nonzero(m_f, as_tuple=True)
        if distinct:
            pick = distinct_pixels(len(ys), n_f, gen).to(ys.device)
        else:
            pick = torch.randint(0, len(ys), (n_f,), generator=gen, device="cpu").to(ys.device)
        footprint = math.sqrt(len(ys) / n_f)
        out.append(_back_project(data, f, ys[pick], xs[pick], footprint))
    if not out:
        return empty
    return tuple(torch.cat(parts) for parts in zip(*out))


def distinct_pixels(available: int, n: int, gen: torch.Generator) -> torch.Tensor:
    """``n`` indices into ``available`` pixels ``[n]``: a random order of all of them, repeated
    (each pass reshuffled) while ``n`` asks for more.

    Why not ``n`` independent draws: with replacement ~37 % of a frame's moving pixels get no
    Gaussian of their own when ``n`` equals their count, and a moving Gaussian with a lifespan
    learns only on the steps that draw its frame (~30 in a run), so the seeds' cover is most
    of what its frame shows (docs/benchmarks.md, *Seeds that cover their frame*). Seeds shown at
    every time overlap with every other frame's anyway; for them the distinct draw measured
    -0.07 dB on the small-motion scenes, so they keep the independent one.
    """
    passes = [torch.randperm(available, generator=gen, device="cpu") for _ in range(-(-n // available))]
    return torch.cat(passes)[:n]


class NodeSubset(torch.nn.Module):
    """Nodes ``sel [S]`` of a model (every node for ``slice(None)``), as the node-only view
    :func:`invert_at_time` reads (indices it returns are into ``sel``)."""

    def __init__(self, model: DynamicScene, sel: torch.Tensor | slice):
        super().__init__()
        self.m, self.sel = model, sel

    def node_state(self, t):
        pos, rot = self.m.node_state(t)
        return pos[self.sel], rot[self.sel]

    def node_radii(self):
        return self.m.node_radii()[self.sel]

    @property
    def node_centers(self):
        return self.m.node_centers[self.sel]


def canonicalise(probe: DynamicScene, pts: torch.Tensor, tms: torch.Tensor, node_sel: torch.Tensor | None,
                 k: int, identity: bool = False) -> torch.Tensor:
    """Map points ``[P, 3]`` observed at times ``tms [P]`` to canonical space through nodes
    ``node_sel`` (all when None); one inversion per distinct time."""
    if identity or len(pts) == 0:
        return pts.clone()
    view = NodeSubset(probe, slice(None) if node_sel is None else node_sel)
    canon = torch.empty_like(pts)
    for t in torch.unique(tms).tolist():  # one inversion per observation time
        sel = tms == t
        canon[sel] = to_canonical(view, pts[sel], t, k)[0]
    return canon


def build_model(data: TrainingData, nodes: B.NodeArrays, cfg: TrainConfig, gen: torch.Generator) -> DynamicScene:
    """Create the model: nodes from ``nodes``, Gaussians back-projected into canonical space.

    With ``cfg.split`` (and a dynamic prior) nodes are classed dynamic / static
    (:func:`engine.train.split.node_dynamic_flags` on the initialiser's ``p_dyn`` and the
    prior along each node's initial trajectory), static nodes are put at rest, the ARAP
    graph links each class within itself, static Gaussians come from the static pixels of
    the keyframes and dynamic ones from the moving pixels of every training frame, mapped
    to canonical space through the dynamic nodes only.
    """
    from .split import graph_within_class, node_dynamic_flags

    dev, dt = data.images.device, torch.float32
    as_t = lambda a: torch.as_tensor(np.asarray(a), device=dev, dtype=dt)  # noqa: E731
    key_times, pos_keys, rot_keys = as_t(nodes.key_times), as_t(nodes.pos_keys), as_t(nodes.rot_keys)
    graph = torch.as_tensor(nodes.graph_idx, device=dev) if nodes.graph_idx is not None else None
    centers, radii = as_t(nodes.centers), as_t(nodes.radii)
    p_dyn = as_t(nodes.p_dyn) if nodes.p_dyn is not None else torch.zeros(len(centers), device=dev)
    fg_score = node_fg_score(data, nodes)
    node_dyn = None
    if cfg.split and fg_score is not None:
        node_dyn = node_dynamic_flags(p_dyn, fg_score, cfg.dynamic_threshold)
        if not bool(node_dyn.any()) or bool(node_dyn.all()):
            node_dyn = None  # nothing moves, or nothing is still: one class
    if node_dyn is not None:
        # static nodes rest where they were seen (their keys never train)
        rest = centers.unsqueeze(1).expand_as(pos_keys)
        pos_keys = torch.where(node_dyn[:, None, None], pos_keys, rest)
        rot_keys = torch.where(node_dyn[:, None, None], rot_keys,
                               quat_identity(*rot_keys.shape[:-1], dtype=rot_keys.dtype, device=rot_keys.device))
    if cfg.motion != "mlp" and cfg.canonical_time >= 0:
        pos_tan = as_t(nodes.pos_tangents) if node_dyn is None else None
        centers, radii, graph = common_canonical_nodes(data, key_times, pos_keys, pos_tan, cfg.canonical_time, graph,
                                                       cfg.radius_k, cfg.radius_factor)
        rot_keys = canonical_rotations(data, key_times, rot_keys, cfg.canonical_time)
    if graph is not None and (node_dyn is not None or cfg.arap_graph == "paths"):
        graph = graph_within_class(centers, node_dyn, graph.shape[1],
                                   paths=pos_keys if cfg.arap_graph == "paths" else None)
    if cfg.motion == "per_frame":
        # one key per training frame, initialised by sampling the initial spline there
        from ..geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_eval_quat

        ft = torch.unique(data.times[data.train_idx]).to(dt)
        pos_tan = as_t(nodes.pos_tangents) if node_dyn is None else catmull_rom_tangents(key_times, pos_keys)
        pos_keys = hermite_eval(key_times, pos_keys, pos_tan, ft)
        rot_keys = hermite_eval_quat(key_times, rot_keys, catmull_rom_tangents(key_times, rot_keys), ft)
        key_times = ft
    # Nodes alone first (one dummy Gaussian) to map observed points to canonical space.
    probe = DynamicScene(centers[:1].clone(), torch.zeros(1, 3, device=dev), torch.ones(1, 3, device=dev),
                         torch.full((1,), 0.5, device=dev), centers, radii, key_times, pos_keys,
                         rot_keys, sh_degree=cfg.sh_degree, motion="spline", bind_k=cfg.bind_k,
                         graph_idx=graph, node_p_dyn=p_dyn, extent=data.extent)
    identity = cfg.motion == "mlp"  # the MLP starts at identity motion
    if node_dyn is None:
        pts, cols, scl, tms = initial_gaussians(data, cfg, gen)
        canon = canonicalise(probe, pts, tms, None, cfg.bind_k, identity)
        g_dyn = None
    else:
        life = data_lifespan(cfg, data)
        s_pts, s_cols, s_scl, _ = initial_gaussians(data, cfg, gen, static_only=True)
        # with lifespans only the moving Gaussians of the frames around t show at t: seed more
        seed_cfg = (dataclasses.replace(cfg, dynamic_gaussians=lifespan_seed_count(cfg, len(data.train_idx)))
                    if life > 0 else cfg)
        d_pts, d_cols, d_scl, d_tms = dynamic_gaussians(data, seed_cfg, gen, distinct=life > 0)
        d_canon = canonicalise(probe, d_pts, d_tms, torch.nonzero(node_dyn).squeeze(1), cfg.bind_k, identity)
        canon = torch.cat([s_pts, d_canon])  # static points are where they were seen
        cols, scl = torch.cat([s_cols, d_cols]), torch.cat([s_scl, d_scl])
        g_dyn = torch.cat([torch.zeros(len(s_pts), dtype=torch.bool, device=dev),
                           torch.ones(len(d_pts), dtype=torch.bool, device=dev)])
    opac = torch.full((len(canon),), 0.3, device=dev)
    if g_dyn is not None and life > 0:
        # a frame's own seeds, shown around it only: opaque, each covers its pixel (distinct_pixels)
        # rather than a third of it. Seeds shown at every time stay at 0.3: dozens of frames' seeds
        # of one object overlap there, and opaque ones cost the small-motion scenes 0.3 dB
        opac[g_dyn] = cfg.lifespan_seed_opacity
    model = DynamicScene(canon, cols.clamp(0, 1), scl, opac, centers,
                         radii, key_times, pos_keys, rot_keys, sh_degree=cfg.sh_degree,
                         motion=cfg.motion, bind_k=cfg.bind_k, graph_idx=graph, node_p_dyn=p_dyn,
                         extent=data.extent)
    if fg_score is not None:
        model.node_fg.copy_(fg_score)
    if node_dyn is not None:
        model.node_dyn = node_dyn.clone()
        model.gauss_dyn = g_dyn
        if life > 0:  # each moving Gaussian lives around the frame it was seeded from
            model.gauss_t_center[len(s_pts):] = d_tms.reshape(-1).to(model.gauss_t_center)
            model.gauss_lifespan[len(s_pts):] = life
        model.rebind()
    return model


def common_canonical_nodes(data: TrainingData, key_times: torch.Tensor, pos_keys: torch.Tensor,
                           pos_tangents: torch.Tensor | None, t_rel: float, graph: torch.Tensor | None,
                           radius_k: int = 4, radius_factor: float = 1.0):
    """Canonical node centres at one shared time: each node's initial position there.

    An initialiser places every node where it was seen, at its own source frame; nodes on a
    moving part seen at different keyframes then sit where the part was at *different*
    times. Used as canonical centres, that mixes times: a Gaussian's canonical position
    blends frames its nodes disagree on, and the canonical K-NN binding (and every rebind)
    can then pick nodes of another part, or static ones, that happen to lie near that
    blend — on a part moving more than its width between keyframes (a forearm) its
    Gaussians lag. Taking every centre at one time ``t_c`` (the training frame nearest
    ``t_rel`` of the way through the training frames) makes canonical space the scene at
    ``t_c``. The node transforms keep their meaning once the rotation keys are re-based to
    ``t_c`` too (:func:`canonical_rotations`; identity keys stay identity); radii and the
    ARAP graph are recomputed from the new centres (at ``t_c`` neighbours are true
    neighbours).

    key_times [K], pos_keys / pos_tangents [N, K, 3] (tangents None: Catmull-Rom of the keys)
    -> centres [N, 3], radii [N], graph [N, k] (``None`` in, ``None`` out).
    """
    from ..geometry.hermite import catmull_rom_tangents, hermite_eval
    from ..nodes.graph import node_graph, node_radii

    if pos_tangents is None:
        pos_tangents = catmull_rom_tangents(key_times, pos_keys)
    t_c = _canonical_time(data, t_rel, pos_keys.dtype)
    centers = hermite_eval(key_times, pos_keys, pos_tangents, t_c)[:, 0]
    radii = node_radii(centers, radius_k, radius_factor)  # the run's radius settings, as the initialiser's
    if graph is not None:
        graph = node_graph(centers, graph.shape[1])[0]
    return centers, radii, graph


def _canonical_time(data: TrainingData, t_rel: float, dtype) -> torch.Tensor:
    """The training frame time ``t_rel`` of the way through the training frames, ``[1]``."""
    times = torch.sort(data.times[data.train_idx].to(dtype)).values
    return times[int(round(t_rel * (len(times) - 1)))].reshape(1)


def canonical_rotations(data: TrainingData, key_times: torch.Tensor, rot_keys: torch.Tensor,
                        t_rel: float) -> torch.Tensor:
    """Rotation keys relative to the canonical time (see :func:`common_canonical_nodes`).

    An initialiser's rotations are relative to each node's source frame; with the centres
    taken at ``t_c`` the node transform ``R_i(t)(x - c_i) + p_i(t)`` must be the identity
    there, so ``q_i'(t) = q_i(t) ⊗ q_i(t_c)⁻¹``. Identity keys stay identity.
    ``key_times [K]``, ``rot_keys [N, K, 4]`` -> ``[N, K, 4]``.
    """
    from ..geometry.hermite import catmull_rom_tangents, hermite_eval_quat

    t_c = _canonical_time(data, t_rel, rot_keys.dtype)
    q_c = hermite_eval_quat(key_times, rot_keys, catmull_rom_tangents(key_times, rot_keys), t_c)  # [N, 1, 4]
    return quat_normalize(quat_mul(rot_keys, quat_conj(quat_normalize(q_c))))


@torch.no_grad()
def node_fg_score(data: TrainingData, nodes: B.NodeArrays, occlusion_tol: float = 0.2) -> torch.Tensor | None:
    """Per-node dynamic score [N] in [0, 1] from the foreground/dynamic prior, the same for
    every initialiser and motion model.

    Each node follows its *initial* trajectory (the spline the initialiser fitted to the
    tracks) through the training frames; the score is :func:`trajectory_fg_score` of it.
    Nodes never in view get the initialiser's ``p_dyn``. None without a prior.
    """
    from ..geometry.hermite import hermite_eval

    if data.fg is None:
        return None
    dev, dt = data.images.device, torch.float32
    as_t = lambda a: torch.as_tensor(np.asarray(a), device=dev, dtype=dt)  # noqa: E731
    times = data.times[data.train_idx].to(dt)
    pos = hermite_eval(as_t(nodes.key_times), as_t(nodes.pos_keys), as_t(nodes.pos_tangents), times)  # [N, T, 3]
    fallback = as_t(nodes.p_dyn) if nodes.p_dyn is not None else torch.zeros(pos.shape[0], device=dev)
    return trajectory_fg_score(data, pos, fallback, occlusion_tol)


def trajectory_fg_score(data: TrainingData, pos: torch.Tensor, fallback: torch.Tensor,
                        occlusion_tol: float = 0.2) -> torch.Tensor:
    """Mean dynamic prior along trajectories ``pos [N, T, 3]`` (world positions at the
    training frames ``data.train_idx``, in that order) -> [N] in [0, 1].

    The prior is read at each position's projection over the frames where it is in view
    and not behind the prior's depth (``occlusion_tol`` relative; merged nodes may sit a
    little inside an object), so a static point that a moving object passes in front of
    stays static. Points never in view get ``fallback [N]``. Requires ``data.fg``.
    """
    h, w = data.height, data.width
    dev = pos.device
    idx = data.train_idx.to(dev)
    # every (point, frame) pair at once: the cameras broadcast over the points
    uv, z = project(data.K[idx][None], data.w2c[idx][None], pos)  # [N, T, 2], [N, T]
    px, py = uv[..., 0].floor().long(), uv[..., 1].floor().long()
    ok = (z > 0) & (px >= 0) & (px < w) & (py >= 0) & (py < h)
    px, py = px.clamp(0, w - 1), py.clamp(0, h - 1)
    ff = idx[None].expand_as(px)
    if data.depth is not None:
        dz = data.depth[ff, py, px]
        ok &= (dz <= 0) | (z <= dz * (1 + occlusion_tol))
    acc = torch.where(ok, data.fg[ff, py, px], 0.0).sum(1)
    cnt = ok.sum(1).to(acc.dtype)
    return torch.where(cnt > 0, acc / cnt.clamp_min(1), fallback.to(dev)).clamp(0, 1)
