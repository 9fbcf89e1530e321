"""The optimisation loop: initialise, train, densify, checkpoint, resume, evaluate.

``Trainer(data, nodes, config, out_dir).run()`` turns :class:`TrainingData` and an
initial node set into a trained result bundle. Long runs are safe to interrupt:
checkpoints are written atomically every ``checkpoint_every`` steps and on SIGINT /
SIGTERM (the CLI turns both into ``KeyboardInterrupt``); ``resume=True`` continues from
the last checkpoint and reproduces the uninterrupted run (CPU, same seed).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from .. import bundle as B
from ..errors import Cancelled, InputError
from ..fsutil import atomic_path
from ..geometry.camera import project, unproject
from ..geometry.dualquat import node_transforms_dq
from ..geometry.quaternion import quat_apply, quat_normalize, quat_to_matrix
from ..protocol import Reporter
from . import checkpoint as CK
from . import losses as L
from .config import TrainConfig
from .data import TrainingData
from .fused_reg import fused_arap, fused_key_terms, fused_reg_available
from .model import DynamicScene
from .phases import no_phase
from .render import render_scene, scene_colors
from .split import freeze_static_nodes, graph_within_class
from .warmup import warm_kernels

GAUSSIAN_PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
CHECKPOINT_NAME = "checkpoint.pt"
#: ARAP / static-motion / smoothness through engine/train/fused_reg.py on the CPU (tests
#: switch it off to compare with the torch versions)
FUSED_REG = True


# build_model / initial_gaussians / trajectory_fg_score re-exported: the model's
# construction lives in init_model.py
from .init_model import build_model, canonicalise, initial_gaussians, trajectory_fg_score  # noqa: F401


# ----------------------------------------------------------------------------------
# Optimiser with per-Gaussian state surgery (densification)
# ----------------------------------------------------------------------------------
def make_optimizer(model: DynamicScene, cfg: TrainConfig) -> torch.optim.Adam:
    e = model.extent
    groups = [
        {"name": "means", "params": [model.means], "lr": cfg.lr_means * e},
        {"name": "quats", "params": [model.quats], "lr": cfg.lr_quats},
        {"name": "log_scales", "params": [model.log_scales], "lr": cfg.lr_scales},
        {"name": "opacity_logits", "params": [model.opacity_logits], "lr": cfg.lr_opacity},
        {"name": "sh_dc", "params": [model.sh_dc], "lr": cfg.lr_sh},
        {"name": "sh_rest", "params": [model.sh_rest], "lr": cfg.lr_sh / 20},
    ]
    if model.mlp is not None:
        groups.append({"name": "mlp", "params": list(model.mlp.parameters()), "lr": cfg.lr_mlp})
    else:
        groups.append({"name": "pos_keys", "params": [model.pos_keys], "lr": cfg.lr_node_keys * e})
        groups.append({"name": "rot_keys", "params": [model.rot_keys], "lr": cfg.lr_node_rot})
    # fused Adam: one kernel per parameter instead of ~10 elementwise ops (about 3x less
    # CPU time for the step; same update to float rounding)
    fused = model.means.device.type in ("cpu", "cuda") and model.means.dtype == torch.float32
    return torch.optim.Adam(groups, eps=1e-15, fused=fused or None)


NODE_PARAMS = ("pos_keys", "rot_keys")  # node_log_radii is a buffer (DynamicScene), edited beside them


def _edit_gaussians(model: DynamicScene, opt: torch.optim.Adam, keep: torch.Tensor | None,
                    extra: dict[str, torch.Tensor] | None, names=GAUSSIAN_PARAMS) -> None:
    """Keep rows ``keep`` of every per-Gaussian (or per-node, with ``names=NODE_PARAMS``)
    parameter and append ``extra`` rows.

    Adam moments follow: kept rows keep theirs, new rows start at zero.
    """
    for group in opt.param_groups:
        name = group["name"]
        if name not in names or extra is not None and name not in extra:
            continue
        old = group["params"][0]
        state = opt.state.pop(old, None)
        data = old.detach()
        if keep is not None:
            data = data[keep]
        if extra is not None:
            data = torch.cat([data, extra[name].to(data.dtype)], 0)
        new = torch.nn.Parameter(data.contiguous())
        if state is not None:
            for key in ("exp_avg", "exp_avg_sq"):
                s = state[key]
                if keep is not None:
                    s = s[keep]
                if extra is not None:
                    s = torch.cat([s, torch.zeros_like(extra[name], dtype=s.dtype)], 0)
                state[key] = s.contiguous()
            opt.state[new] = state
        group["params"][0] = new
        setattr(model, name, new)


# ----------------------------------------------------------------------------------
# Trainer
# ----------------------------------------------------------------------------------
class Trainer:
    """Runs one reconstruction.

    Parameters
    ----------
    data : TrainingData
    nodes : bundle.NodeArrays
        Initial node set (from ``engine.nodes``).
    config : TrainConfig
    out_dir : path
        The result bundle folder (checkpoints go to ``out_dir/checkpoints``).
    reporter : Reporter, optional
    resume : bool
        Continue from ``out_dir/checkpoints/checkpoint.pt``.
    scene_extra : dict, optional
        Extra scene.json keys (source clip, priors, camera solve).
    still_plate : dict, optional
        ``{"train": dB, "val": dB}``: the still plate's PSNR, logged and recorded beside the
        run's own (``engine.pipeline.still_plate_psnr``).
    """

    def __init__(self, data: TrainingData, nodes: B.NodeArrays, config: TrainConfig, out_dir,
                 reporter: Reporter | None = None, resume: bool = False, scene_extra: dict | None = None,
                 still_plate: dict | None = None):
        self.data = data.validate()
        self.nodes = nodes
        self.cfg = config.validate()
        self.out_dir = Path(out_dir)
        self.ckpt_path = self.out_dir / "checkpoints" / CHECKPOINT_NAME
        self.reporter = reporter or Reporter(quiet=True)
        self.scene_extra = scene_extra or {}
        self.still_plate = still_plate
        self.device = data.images.device
        torch.manual_seed(self.cfg.seed)
        # bitwise resume on the CPU needs deterministic algorithms: a process-wide switch,
        # set where the process starts (engine/runtime.py), not here
        self.gen = torch.Generator(device="cpu")
        self.gen.manual_seed(self.cfg.seed)
        self.step = 0
        self.history: list[dict] = []
        self.train_seconds = 0.0
        self.initial_eval: dict | None = None
        self.track_canon = None
        # initial keys of every node [N, K, 3] / [N, K, 4] (spline / per-frame motion): the
        # reference of the static-motion term; kept only when loss.static_init > 0
        self.static_ref = None
        # a PhaseTimer (engine/train/phases.py) when a bench profiles the step; None in runs
        self.phases = None
        # which run this is (data + config hashes): stored in checkpoints, checked on resume
        self.identity = CK.run_identity(self.data, self.cfg)
        if resume and self.ckpt_path.exists():
            self._load_checkpoint()
        else:
            if resume:
                B.refuse_finished_resume(self.out_dir)
                self.reporter.log(f"no checkpoint at {self.ckpt_path}; starting a new run", "warning")
            self.model = build_model(self.data, nodes, self.cfg, self.gen)  # sets node_fg too
            self.opt = make_optimizer(self.model, self.cfg)
            self._reset_densify_stats()
            self._prepare_tracks()
            if self.model.pos_keys is not None and self.cfg.loss.static_init > 0:
                self.static_ref = (self.model.pos_keys.detach().clone(), self.model.rot_keys.detach().clone())

    # ---------------------------------------------------------------- helpers
    def _reset_densify_stats(self):
        g = self.model.num_gaussians
        self.grad_accum = torch.zeros(g, device=self.device)
        self.grad_count = torch.zeros(g, device=self.device)

    def _prepare_tracks(self):
        """Lift each track once (first visible frame + depth) and map it to canonical space."""
        d = self.data
        if d.tracks_xy is None or d.depth is None or self.cfg.loss.track == 0 or self.model.mlp is not None:
            return
        vis = d.tracks_vis.clone()
        vis[:, d.val_idx] = False  # never supervise with held-out frames
        has = vis.any(1)
        if self.model.is_split and d.fg is not None:
            # static tracks would only pull on frozen static nodes: supervise the moving ones
            has &= self._moving_tracks(vis)
        if has.sum() == 0:
            return
        first = torch.argmax(vis.to(torch.int8), dim=1)
        pid = torch.nonzero(has).squeeze(1)
        f0 = first[pid]
        uv = d.tracks_xy[pid, f0]
        h, w = d.height, d.width
        px = uv[:, 0].long().clamp(0, w - 1)
        py = uv[:, 1].long().clamp(0, h - 1)
        z = d.depth[f0, py, px]
        ok = z > 0
        pid, f0, uv, z = pid[ok], f0[ok], uv[ok], z[ok]
        m = self.model
        x = unproject(d.K[f0], d.w2c[f0], uv, z)
        # with the split, mapped and bound through the dynamic nodes only (moving tracks)
        dyn = torch.nonzero(m.node_dyn).squeeze(1) if m.is_split else None
        canon = canonicalise(m, x, d.times[f0].to(x.dtype), dyn, m.bind_k)
        idx, wts = m.bind_points(canon)
        self.track_ids, self.track_canon, self.track_idx, self.track_w = pid, canon, idx, wts
        self.track_vis = vis

    def _moving_tracks(self, vis: torch.Tensor) -> torch.Tensor:
        """``[P] bool``: tracks whose median dynamic prior over their visible frames reaches
        ``cfg.dynamic_threshold``."""
        from ..priors.dynamic_depth import moving_tracks

        d = self.data
        return torch.as_tensor(moving_tracks(d.tracks_xy.cpu().numpy(), vis.cpu().numpy(), d.fg.cpu().numpy(),
                                             self.cfg.dynamic_threshold), device=vis.device)

    def _rebind(self):
        """Refresh the binding of the Gaussians and of the lifted track points together.

        The track points are bound like Gaussians (canonical position -> K nearest nodes).
        Node densification renumbers the nodes (pruned ones leave gaps, spawned ones are
        appended), so a binding kept from before addresses the wrong nodes, or none: the
        fused deformation kernel does not bounds-check, and a run whose densification
        pruned a node crashed with heap corruption.
        """
        m = self.model
        m.rebind()
        if self.track_canon is not None:
            with torch.no_grad():
                idx, w = m.bind_points(self.track_canon)
            self.track_idx, self.track_w = idx, w.to(self.track_w.dtype)

    def _lr_schedule(self):
        if self.cfg.steps <= 1:
            return
        frac = min(self.step / self.cfg.steps, 1.0)
        e = self.model.extent
        def decay(a, b):
            return math.exp((1 - frac) * math.log(a) + frac * math.log(b)) if a > 0 and b > 0 else (1 - frac) * a + frac * b

        # spline keys decay like the Gaussian means (log-linear): at a constant rate the
        # per-frame photometric noise keeps moving them (static nodes drifted ~3 px), which
        # blurs everything they carry in the held-out view
        lrs = {"means": decay(self.cfg.lr_means * e, self.cfg.lr_means_final * e),
               "pos_keys": decay(self.cfg.lr_node_keys * e, self.cfg.lr_node_keys_final * e),
               "rot_keys": decay(self.cfg.lr_node_rot, self.cfg.lr_node_rot_final),
               # the MLP baseline decays the same way (SC-GS decays its deformation lr too)
               "mlp": decay(self.cfg.lr_mlp, self.cfg.lr_mlp_final)}
        for group in self.opt.param_groups:
            if group["name"] in lrs:
                group["lr"] = lrs[group["name"]]

    # ---------------------------------------------------------------- one step
    def _loss(self, f: int) -> tuple[torch.Tensor, dict]:
        d, m, w = self.data, self.model, self.cfg.loss
        ph = self.phases or no_phase
        t = float(d.times[f])
        with ph("deform"):
            # node state at t once per step: the deformation, the track term and ARAP share it
            pos_t, rot_t = m.node_state(t)
            dq_nodes = node_transforms_dq(m.node_centers, pos_t, rot_t)
            means_t, quats_t = m.deform(t, dq_nodes=dq_nodes)
        with ph("sh"):  # the colour raster.render would compute from sh=..., timed on its own
            colors = scene_colors(m, means_t, d.w2c[f])
        # the mask term (every 4th step) renders the Gaussians' dynamic score as an extra
        # channel of the colour pass instead of a second render
        mask_now = w.mask > 0 and d.fg is not None and self.step % 4 == 0
        with ph("raster_fwd"):
            out = render_scene(m, means_t, quats_t, d.K[f], d.w2c[f], d.width, d.height, colors=colors,
                               backend=self.cfg.backend, extra=self._dynamic_score() if mask_now else None)
        with ph("losses"):
            return self._loss_terms(f, t, out, means_t, quats_t, (pos_t, rot_t, dq_nodes))

    def _loss_terms(self, f: int, t: float, out, means_t: torch.Tensor, quats_t: torch.Tensor, nodes_t):
        """The loss terms of frame ``f``; ``nodes_t`` = node positions [N, 3], rotations
        [N, 4] and dual quaternions [N, 8] at ``t`` (computed once by :meth:`_loss`)."""
        d, m, w = self.data, self.model, self.cfg.loss
        pos_t, rot_t, dq_nodes = nodes_t
        target = d.images[f]
        weight = None
        if w.rgb_dynamic > 0 and d.fg is not None:
            # moving pixels are a few % of the image: weight them up so the objects get a
            # share of the photometric gradient that is not drowned by the background
            weight = (1.0 + w.rgb_dynamic * (d.fg[f] >= self.cfg.dynamic_threshold).to(target.dtype)).unsqueeze(-1)
        terms = {"rgb": L.photometric(out.rgb, target, w.ssim, weight) * w.rgb}
        if w.depth > 0 and d.depth is not None:
            prior = d.depth[f]
            valid = (prior > 0) & (out.alpha[..., 0].detach() > 0.5)
            # the rasteriser accumulates sum(w_i z_i); divide by alpha for the expected depth
            depth = out.depth[..., 0] / out.alpha[..., 0].detach().clamp_min(1e-6)
            terms["depth"] = w.depth * L.depth_shift_scale_invariant(depth, prior, valid)
        if out.extra is not None:  # a mask step (see _loss)
            terms["mask"] = w.mask * L.mask_loss(out.alpha, out.extra, d.fg[f])
        if self.track_canon is not None and w.track > 0 and self.step >= self.cfg.warmup_static_steps:
            vis = self.track_vis[self.track_ids, f]
            if vis.any():
                sel = torch.nonzero(vis).squeeze(1)
                if len(sel) > 1024:
                    sel = sel[torch.randperm(len(sel), generator=self.gen)[:1024].to(sel.device)]
                x = m.deform_points(self.track_canon[sel], self.track_idx[sel], self.track_w[sel], t,
                                    dq_nodes=dq_nodes)
                uv, _ = project(d.K[f], d.w2c[f], x)
                target_uv = d.tracks_xy[self.track_ids[sel], f]
                # in % of the image width (Huber, linear beyond 0.05 %): at the width of the
                # image the term vanished next to the photometric one (a 10 px error cost 1e-4)
                terms["track"] = w.track * L.track_loss(uv, target_uv, torch.ones_like(sel, dtype=torch.bool),
                                                        float(d.width) / 100.0)
        motion_on = self.step >= self.cfg.warmup_static_steps
        arap_on = w.arap > 0 and m.graph_idx.shape[1] > 0 and motion_on
        static_on = w.static > 0 and motion_on
        smooth_on = m.pos_keys is not None and (w.velocity > 0 or w.acceleration > 0) and self.cfg.motion == "spline"
        # the node-graph terms in one Numba pass each on the CPU (engine/train/fused_reg.py;
        # the torch versions below are their references and the CUDA path)
        fused = FUSED_REG and fused_reg_available(pos_t)
        state_t1 = None
        if arap_on or static_on and m.mlp is not None:
            # a second random time, shared by ARAP and the MLP's static-motion term
            t1 = float(torch.rand((), generator=self.gen))
            state_t1 = m.node_state(t1)
        if arap_on:
            arap = fused_arap if fused else L.arap_states
            terms["arap"] = w.arap * arap(pos_t, rot_t, *state_t1, m.graph_idx) / (m.extent ** 2)
        if fused and m.pos_keys is not None and (smooth_on or static_on):
            st, vel, acc = fused_key_terms(m.pos_keys, m.rot_keys, m.key_times, *self._static_weights(), m.extent,
                                           *self._static_reference())
            smooth = (vel, acc)
        else:
            st = self._static_motion(pos_t, rot_t, state_t1) if static_on else None
            smooth = L.spline_smoothness(m.pos_keys / m.extent, m.key_times) if smooth_on else None
        if smooth_on:
            terms["velocity"] = w.velocity * smooth[0]
            terms["acceleration"] = w.acceleration * smooth[1]
        if static_on:
            terms["static"] = w.static * st
        loss = sum(terms.values())
        with torch.no_grad():
            metrics = {k: float(v) for k, v in terms.items()}
            metrics["psnr"] = float(L.psnr(out.rgb.clamp(0, 1), target))
        return loss, metrics, out

    def _static_motion(self, pos_t: torch.Tensor, rot_t: torch.Tensor, state_t1=None) -> torch.Tensor:
        """Motion of the nodes the prior calls static: ``mean_i (1 − s_i) e_i`` with ``s_i`` the
        node's foreground score (:func:`node_fg_score`, the same for every initialiser).

        ``e_i`` is the variance over time of the node's position and rotation, in units of
        the scene extent, so a constant trajectory (any fixed offset) costs nothing. Keyed
        motion (spline, per_frame) computes it exactly over its keys; the MLP estimates it
        without bias from this step's time ``t`` and a second random time ``t1``
        (``state_t1`` = positions and rotations there) as ``½|x(t) − x(t1)|²``
        (``E|x(t) − x(t1)|² = 2 Var x``). Rotation is measured as the displacement it causes
        at the node's radius (``2ρ|Δq|``), so a large static node pays for turning the
        Gaussians far from its centre. With ``loss.static_init = a > 0`` keyed motion is
        measured relative to ``a`` times the node's initial keys (:attr:`static_ref`).
        """
        m = self.model
        s, arm = self._static_weights()
        if m.pos_keys is not None:
            return L.static_motion_keys(m.pos_keys, m.rot_keys, s, arm, m.extent, *self._static_reference())
        pos_1, rot_1 = state_t1
        e = 0.5 * ((((pos_t - pos_1) / m.extent) ** 2).sum(-1) + ((rot_t - rot_1) ** 2).sum(-1) * arm)
        return (s * e).mean()  # a mean over nodes, like ARAP and smoothness

    def _static_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The static-motion term's per-node weight ``(1 − fg)^power`` and rotation arm
        ``(2ρ / extent)²``, both [N] constants."""
        m = self.model
        s = (1.0 - m.node_fg).clamp(0, 1) ** self.cfg.loss.static_power
        if m.is_split:  # a dynamic node is never held still; static ones are frozen anyway
            s = torch.where(m.node_dyn, torch.zeros_like(s), s)
        arm = (2.0 * m.node_radii().detach() / m.extent) ** 2
        return s, arm

    def _static_reference(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """``(a · initial pos keys, a · normalised initial rot keys)`` with ``a =
        loss.static_init``, or ``(None, None)``: motion beyond the initial trajectory, so a
        node on a thin moving part that the prior half-calls static keeps the motion its
        tracks gave it."""
        if self.static_ref is None:
            return None, None
        a = self.cfg.loss.static_init
        return a * self.static_ref[0], a * quat_normalize(self.static_ref[1])

    def _dynamic_score(self) -> torch.Tensor:
        """Per-Gaussian dynamic score [G] for the mask term (the colour pass's extra
        channel): the Gaussian's class with the split, else the bound nodes' ``p_dyn``
        blended by the binding weights. It changes only
        when the binding or the nodes do (rebind / densification assign new tensors), so it
        is cached on the identity and version of its inputs."""
        m = self.model
        if m.is_split:  # the class itself: dynamic Gaussians should cover the moving pixels
            key, score = (m.gauss_dyn,), lambda: m.gauss_dyn.to(m.means.dtype)
        else:
            key, score = (m.bind_idx, m.bind_w, m.node_p_dyn), lambda: (m.node_p_dyn[m.bind_idx] * m.bind_w).sum(-1)
        versions = tuple(x._version for x in key)
        c = getattr(self, "_dyn_cache", None)
        if c is None or len(c[0]) != len(key) or any(a is not b for a, b in zip(c[0], key)) or c[1] != versions:
            self._dyn_cache = c = (key, versions, score().contiguous())
        return c[2]

    def _densify(self):
        cfg, m = self.cfg, self.model
        with torch.no_grad():
            grads = self.grad_accum / self.grad_count.clamp_min(1)
            scales = m.scales().max(dim=1).values
            big = scales > cfg.percent_dense * m.extent
            hot = grads >= cfg.densify_grad_threshold
            room = max(cfg.max_gaussians - m.num_gaussians, 0)
            clone = torch.nonzero(hot & ~big).squeeze(1)
            split = torch.nonzero(hot & big).squeeze(1)
            # respect the budget: keep the hottest candidates
            if len(clone) + len(split) > room:
                cand = torch.cat([clone, split])
                order = torch.argsort(grads[cand], descending=True)[:room]
                chosen = cand[order]
                clone = chosen[~big[chosen]]
                split = chosen[big[chosen]]
            extra = {}
            if len(clone) or len(split):
                src = torch.cat([clone, split])
                std = m.scales()[split]
                noise = torch.randn(std.shape, generator=self.gen).to(std) * std
                rot = quat_to_matrix(quat_normalize(m.quats[split]))
                offset = torch.zeros(len(src), 3, device=self.device)
                offset[len(clone):] = (rot @ noise.unsqueeze(-1)).squeeze(-1)
                extra = {name: getattr(m, name).detach()[src].clone() for name in GAUSSIAN_PARAMS}
                extra["means"] = extra["means"] + offset
                extra["log_scales"][len(clone):] -= math.log(1.6)
                # the split originals shrink too
                m.log_scales.data[split] -= math.log(1.6)
            keep = m.opacities() > cfg.opacity_prune
            g_dyn = m.gauss_dyn[keep]
            if extra:
                g_dyn = torch.cat([g_dyn, m.gauss_dyn[src]])
            _edit_gaussians(m, self.opt, keep, extra or None)
            m.gauss_dyn = g_dyn.contiguous()
            self._rebind()
            if cfg.node_densify:
                self._densify_nodes()
            self._reset_densify_stats()

    def _densify_nodes(self):
        """Add nodes where Gaussians are far from every node; drop nodes nobody uses.

        A Gaussian farther than ``node_spawn_factor`` times its nearest node's radius is
        poorly controlled. Up to ``node_add_max`` such Gaussians (farthest-point spread)
        become new nodes that start with their parent node's motion, shifted to their
        position; nodes whose summed binding weight is ~0 are removed. The graph and the
        binding are rebuilt afterwards.
        """
        from ..nodes.baselines import farthest_point_sampling
        from ..nodes.graph import node_graph

        cfg, m = self.cfg, self.model
        with torch.no_grad():
            n = m.num_nodes
            load = torch.zeros(n, device=self.device).index_add_(0, m.bind_idx.reshape(-1),
                                                                 m.bind_w.reshape(-1).to(torch.float32))
            keep = load >= cfg.node_prune_weight
            if int(keep.sum()) < m.bind_k:
                keep[:] = True
            parent = m.bind_idx[:, 0]
            dist = (m.means - m.node_centers[parent]).norm(dim=-1)
            far = torch.nonzero(dist > cfg.node_spawn_factor * m.node_radii()[parent]).squeeze(1)
            cap = int(cfg.max_nodes_factor * cfg.num_nodes)
            room = max(0, min(cfg.node_add_max, cap - int(keep.sum())))
            extra = None
            if len(far) and room:
                pick = far[farthest_point_sampling(m.means[far].cpu(), room, cfg.seed).to(self.device)]
                par = parent[pick]
                new_c = m.means[pick].detach().clone()
                extra = {"node_log_radii": m.node_log_radii[par].detach().clone()}
                if m.is_split:  # a spawned node is of its parent's class (a static one rests)
                    follow, spawn_fg = m.node_dyn[par].clone(), m.node_fg[par].clone()
                else:
                    follow, spawn_fg = self._spawn_motion(par, new_c)
                if m.pos_keys is not None:
                    # a following node starts with exactly its parent's rigid motion: at each
                    # key p_new = p_par + R_par (c_new − c_par) (without R_par the Gaussians
                    # it takes over would jump by (I − R_par)(c_new − c_par)); a static one
                    # stays at c_new with the identity rotation
                    rk = m.rot_keys[par].detach()
                    shift = (new_c - m.node_centers[par]).unsqueeze(1).expand(-1, rk.shape[1], -1)
                    keys = m.pos_keys[par].detach() + quat_apply(quat_normalize(rk), shift)
                    ident = torch.zeros_like(rk)
                    ident[..., 0] = 1.0
                    fol = follow[:, None, None]
                    extra["pos_keys"] = torch.where(fol, keys, new_c.unsqueeze(1).expand_as(keys))
                    extra["rot_keys"] = torch.where(fol, rk, ident)
                new_centers = torch.cat([m.node_centers[keep], new_c])
                new_pdyn = torch.cat([m.node_p_dyn[keep], m.node_p_dyn[par]])
                new_fg = torch.cat([m.node_fg[keep], spawn_fg])
                new_dyn = torch.cat([m.node_dyn[keep], follow if m.is_split else torch.ones_like(follow)])
            elif bool(keep.all()):
                return
            else:
                new_centers, new_pdyn, new_fg = m.node_centers[keep], m.node_p_dyn[keep], m.node_fg[keep]
                new_dyn = m.node_dyn[keep]
            if self.static_ref is not None:  # spawned nodes: their starting keys are their reference
                ref_p, ref_q = self.static_ref[0][keep], self.static_ref[1][keep]
                if extra is not None and "pos_keys" in extra:
                    ref_p = torch.cat([ref_p, extra["pos_keys"]])
                    ref_q = torch.cat([ref_q, extra["rot_keys"]])
                self.static_ref = (ref_p.contiguous(), ref_q.contiguous())
            _edit_gaussians(m, self.opt, keep, extra, names=NODE_PARAMS)
            radii = m.node_log_radii[keep]
            m.node_log_radii = (radii if extra is None else torch.cat([radii, extra["node_log_radii"]])).contiguous()
            m.node_centers = new_centers.contiguous()
            m.node_p_dyn = new_pdyn.contiguous()
            m.node_fg = new_fg.contiguous()
            m.node_dyn = new_dyn.contiguous()
            k = m.graph_idx.shape[1] if m.graph_idx.numel() else 0
            if k and m.is_split:
                m.graph_idx = graph_within_class(new_centers, m.node_dyn, k)
            elif k:
                m.graph_idx = node_graph(new_centers.cpu(), k)[0].to(self.device)
            self._rebind()

    def _spawn_motion(self, par: torch.Tensor, new_c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Whether each node to spawn at ``new_c [S, 3]`` follows its parent ``par [S]``'s
        motion, and its foreground score: ``(follow [S] bool, node_fg [S])``.

        The Gaussians that ask for a node are those far from their nearest node, and near a
        densely sampled moving object (MANI puts many small nodes there) that nearest node is
        often a moving one even for static background. Inheriting its motion and score put
        moving, unpenalised nodes into the background (in a MANI run ~100 of them, which
        dragged ~8 % of the static Gaussians by 0.02-0.09 units). So the prior decides:
        the spot is scored along the parent-following trajectory and at rest
        (:func:`trajectory_fg_score`); the node follows when either score is >= 0.5 and is
        static otherwise. Without a prior every node follows, with its parent's score.
        """
        m, d = self.model, self.data
        follow = torch.ones(len(par), dtype=torch.bool, device=new_c.device)
        if d.fg is None or not len(par):
            return follow, m.node_fg[par]
        p, q = m.node_states(d.times[d.train_idx].tolist(), par)  # [S, T, 3], [S, T, 4]
        offset = (new_c - m.node_centers[par]).unsqueeze(1).expand(-1, p.shape[1], -1)
        follow_pos = p + quat_apply(q, offset)  # [S, T, 3] (densification runs under no_grad)
        fallback = m.node_fg[par]
        fg_follow = trajectory_fg_score(d, follow_pos, fallback)
        fg_static = trajectory_fg_score(d, new_c.unsqueeze(1).expand_as(follow_pos), fallback)
        follow = (fg_follow >= 0.5) | (fg_static >= 0.5)
        score = torch.where(fg_follow >= 0.5, fg_follow, torch.where(follow, fallback, fg_static))
        return follow, score

    def _reset_opacity(self):
        with torch.no_grad():
            self.model.opacity_logits.data.clamp_(max=math.log(0.01 / 0.99))
        for group in self.opt.param_groups:
            if group["name"] == "opacity_logits":
                st = self.opt.state.get(group["params"][0])
                if st:
                    st["exp_avg"].zero_()
                    st["exp_avg_sq"].zero_()

    # ---------------------------------------------------------------- checkpoints
    def _checkpoint_state(self) -> dict:
        return {
            "step": self.step,
            "identity": self.identity,
            "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
            "optimizer": self.opt.state_dict(),
            "gen": self._gen_state if getattr(self, "_gen_state", None) is not None else self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "grad_accum": self.grad_accum.cpu(), "grad_count": self.grad_count.cpu(),
            "history": [[h["step"], h["loss"], h["psnr"]] for h in self.history],
            "train_seconds": self.train_seconds,
            "initial_eval": {k: float(v) for k, v in (self.initial_eval or {}).items()},
            # lifted track anchors are computed once from the initial model; a resumed
            # run must reuse them to reproduce the uninterrupted run
            "tracks": None if self.track_canon is None else {
                "ids": self.track_ids.cpu(), "canon": self.track_canon.cpu(), "idx": self.track_idx.cpu(),
                "w": self.track_w.cpu(), "vis": self.track_vis.cpu()},
            "static_ref": None if self.static_ref is None else [x.cpu() for x in self.static_ref],
        }

    def save_checkpoint(self) -> Path:
        with atomic_path(self.ckpt_path) as tmp:
            torch.save(self._checkpoint_state(), tmp)
        return self.ckpt_path

    def _load_checkpoint(self):
        state = CK.load_state(self.ckpt_path)
        CK.check_identity(state, self.identity, self.ckpt_path)
        try:
            self._restore(state)
        except (KeyError, RuntimeError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(f"checkpoint does not match this run's model ({type(exc).__name__}: "
                             f"{str(exc).splitlines()[0][:120]})", self.ckpt_path,
                             "delete the checkpoints folder to start over, or pass --overwrite") from None
        self.reporter.log(f"resumed from step {self.step} ({self.ckpt_path})")

    def _restore(self, state: dict) -> None:
        sd = state["model"]
        dev = self.device
        if "node_fg" not in sd:  # a checkpoint from before the static-motion score
            sd["node_fg"] = torch.zeros_like(sd["node_p_dyn"])
        # a checkpoint from before the static / dynamic split: one class
        sd.setdefault("node_dyn", torch.ones(sd["node_p_dyn"].shape, dtype=torch.bool))
        sd.setdefault("gauss_dyn", torch.ones(sd["means"].shape[0], dtype=torch.bool))
        g = sd["means"].shape[0]
        gen = torch.Generator()
        gen.manual_seed(0)
        # Rebuild the model with the checkpoint's shapes, then load exact values.
        nodes_keys = sd.get("pos_keys")
        model = DynamicScene(sd["means"].to(dev), torch.zeros(g, 3, device=dev), torch.ones(g, 3, device=dev),
                             torch.full((g,), 0.5, device=dev), sd["node_centers"].to(dev),
                             torch.exp(sd["node_log_radii"]).to(dev), sd["key_times"].to(dev),
                             (nodes_keys if nodes_keys is not None else
                              sd["node_centers"][:, None].expand(-1, len(sd["key_times"]), 3)).to(dev),
                             sd.get("rot_keys", None).to(dev) if sd.get("rot_keys") is not None else None,
                             sh_degree=self.cfg.sh_degree, motion=self.cfg.motion, bind_k=self.cfg.bind_k,
                             graph_idx=sd["graph_idx"].to(dev), node_p_dyn=sd["node_p_dyn"].to(dev),
                             extent=self.data.extent)
        model.load_state_dict({k: v.to(dev) for k, v in sd.items()})
        self.model = model
        self.opt = make_optimizer(model, self.cfg)
        self.opt.load_state_dict(CK.without_groups(state["optimizer"], ("node_log_radii",)))
        self.gen.set_state(state["gen"])
        torch.set_rng_state(state["torch_rng"])
        self.step = int(state["step"])
        self.grad_accum = state["grad_accum"].to(dev)
        self.grad_count = state["grad_count"].to(dev)
        self.history = [{"step": int(s), "loss": float(lo), "psnr": float(p)} for s, lo, p in state["history"]]
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.initial_eval = dict(state.get("initial_eval") or {}) or None
        ref = state.get("static_ref")  # absent in checkpoints from before static_init
        keep_ref = ref is not None and self.cfg.loss.static_init > 0
        self.static_ref = tuple(x.to(dev) for x in ref) if keep_ref else None
        tracks = state.get("tracks")
        if tracks is not None:
            self.track_ids, self.track_canon = tracks["ids"].to(dev), tracks["canon"].to(dev)
            self.track_idx, self.track_w, self.track_vis = tracks["idx"].to(dev), tracks["w"].to(dev), tracks["vis"].to(dev)

    # ---------------------------------------------------------------- main loop
    def train(self) -> None:
        cfg, d = self.cfg, self.data
        train_idx = d.train_idx.cpu()
        motion_groups = {"pos_keys", "rot_keys", "mlp"}
        t_start = time.perf_counter()
        self._stop_requested = False
        previous = self._install_stop_handlers()
        # Deterministic mode NaN-fills every torch.empty (a debugging aid): a fill_ per
        # allocation, a sixth of the step at 240x180 before the fused kernels. The step
        # reads no uninitialised memory (torch.linalg.lstsq on the CPU does, so the depth
        # fit solves its 2x2 normal equations instead), so the loop runs without it; the
        # previous setting is restored on exit, for code outside the loop.
        previous_fill = torch.utils.deterministic.fill_uninitialized_memory
        torch.utils.deterministic.fill_uninitialized_memory = False
        if self.step < cfg.steps:  # starts the stage's clock: the first logged step has a measured ETA
            self.reporter.progress("train", self.step, cfg.steps)
        try:
            while self.step < cfg.steps:
                if self._stop_requested:  # SIGINT/SIGTERM: stop at a step boundary
                    raise KeyboardInterrupt
                self._gen_state = self.gen.get_state()
                f = int(train_idx[torch.randint(0, len(train_idx), (1,), generator=self.gen)])
                self._lr_schedule()
                ph = self.phases or no_phase
                loss, metrics, out = self._loss(f)
                self.opt.zero_grad(set_to_none=True)
                with ph("backward"):
                    loss.backward()
                if self.model.is_split and self.model.pos_keys is not None:
                    freeze_static_nodes(self.model.pos_keys, self.model.rot_keys, self.model.node_dyn)
                if self.step < cfg.warmup_static_steps:  # static warm-up: motion frozen
                    for group in self.opt.param_groups:
                        if group["name"] in motion_groups:
                            for p in group["params"]:
                                p.grad = None
                with ph("optimizer"):
                    self.opt.step()
                with torch.no_grad(), ph("densify_stats"):
                    grad2d = out.grad2d()
                    if grad2d is not None and cfg.densify_from <= self.step < cfg.densify_until:
                        vis = out.radii.reshape(-1) > 0
                        gn = grad2d.norm(dim=-1)
                        # gradient in NDC-like units: scale pixel gradients by half the image size
                        gn = gn * 0.5 * max(d.width, d.height)
                        # dense updates instead of boolean-mask gather/scatter, same values:
                        # invisible Gaussians add exactly 0
                        self.grad_accum += torch.where(vis, gn, 0.0)
                        self.grad_count += vis
                self.step += 1
                # the step's frame draw is done: a checkpoint from here on stores the sampler
                # state after it, so a resume draws the next step's frame, not this one again
                self._gen_state = None
                if cfg.densify_from <= self.step < cfg.densify_until and self.step % cfg.densify_every == 0:
                    self._densify()
                elif cfg.rebind_every and self.step % cfg.rebind_every == 0:
                    self._rebind()
                if cfg.opacity_reset_every and self.step % cfg.opacity_reset_every == 0 and self.step < cfg.densify_until:
                    self._reset_opacity()
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    total = sum(v for k, v in metrics.items() if k != "psnr")
                    self.history.append({"step": self.step, "loss": total, "psnr": metrics["psnr"]})
                    self.reporter.progress("train", self.step, cfg.steps, loss=total, psnr=metrics["psnr"],
                                           gaussians=self.model.num_gaussians)
                if cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0 and self.step < cfg.steps:
                    self.train_seconds += time.perf_counter() - t_start
                    t_start = time.perf_counter()
                    self.save_checkpoint()
                self._gen_state = None
        except KeyboardInterrupt:
            # A KeyboardInterrupt raised mid-step (no handler installed, e.g. off the
            # main thread) loses that step's work; the sampler state is rewound to the
            # step's start so a resume replays it exactly.
            self.train_seconds += time.perf_counter() - t_start
            path = self.save_checkpoint()
            raise Cancelled(f"training stopped at step {self.step}; checkpoint saved to {path}") from None
        finally:
            torch.utils.deterministic.fill_uninitialized_memory = previous_fill
            self._restore_stop_handlers(previous)
        self.train_seconds += time.perf_counter() - t_start

    def request_stop(self) -> None:
        """Ask the loop to checkpoint and stop after the current step (thread-safe)."""
        self._stop_requested = True

    def _install_stop_handlers(self):
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return None
        handler = lambda signum, frame: self.request_stop()  # noqa: E731
        return {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}

    @staticmethod
    def _restore_stop_handlers(previous):
        import signal

        for sig, old in (previous or {}).items():
            signal.signal(sig, old)

    # ---------------------------------------------------------------- evaluation
    @torch.no_grad()
    def render_frame(self, f: int, t: float | None = None):
        d, m = self.data, self.model
        t = float(d.times[f]) if t is None else t
        means_t, quats_t = m.deform(t)
        return render_scene(m, means_t, quats_t, d.K[f], d.w2c[f], d.width, d.height, backend=self.cfg.backend)

    @torch.no_grad()
    def evaluate(self, idx: torch.Tensor | None = None) -> dict:
        """PSNR / SSIM (and masked PSNR where a fg prior exists) on frames ``idx`` (default: val)."""
        d = self.data
        idx = d.val_idx if idx is None else idx
        if len(idx) == 0:
            return {"frames": 0}
        ps, ss, mps = [], [], []
        for f in idx.tolist():
            out = self.render_frame(f)
            pred = out.rgb.clamp(0, 1)
            ps.append(float(L.psnr(pred, d.images[f])))
            ss.append(float(L.ssim(pred, d.images[f])))
            if d.fg is not None and float(d.fg[f].sum()) > 16:
                mps.append(float(L.psnr(pred, d.images[f], (d.fg[f] > 0.5).to(pred.dtype).unsqueeze(-1))))
        res = {"frames": len(ps), "psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}
        if mps:
            res["masked_psnr"] = float(np.mean(mps))
        return res

    def _train_sample(self, at_most: int = 30) -> torch.Tensor:
        """Up to ``at_most`` training frames spread over the clip (the training-view score)."""
        idx = self.data.train_idx
        if len(idx) <= at_most:
            return idx
        return idx[torch.linspace(0, len(idx) - 1, at_most).round().long()]

    def _log_quality(self, metrics: dict) -> None:
        """One line per split: whole-image PSNR beside the still plate's."""
        plate = metrics.get("still_plate") or {}
        for key, split, name in (("eval_train", "train", "training frames"), ("eval", "val", "held-out frames")):
            ev = metrics.get(key) or {}
            if not ev.get("frames"):
                continue
            line = f"{name}: PSNR {ev['psnr']:.2f} dB over {ev['frames']}"
            if plate.get(split) is not None:
                line += f" (still plate {plate[split]:.2f} dB, {ev['psnr'] - plate[split]:+.2f})"
            self.reporter.log(line)

    # ---------------------------------------------------------------- export
    def export_bundle(self, metrics: dict | None = None) -> Path:
        m, d = self.model, self.data
        key_times, pos_keys, pos_tan, rot_keys, rot_tan = m.export_splines()
        nodes = B.NodeArrays(
            centers=m.node_centers.cpu().numpy(), radii=m.node_radii().detach().cpu().numpy(),
            key_times=key_times.cpu().numpy(), pos_keys=pos_keys.cpu().numpy(), pos_tangents=pos_tan.cpu().numpy(),
            rot_keys=rot_keys.cpu().numpy(), rot_tangents=rot_tan.cpu().numpy(),
            p_dyn=m.node_p_dyn.cpu().numpy(), bind_idx=m.bind_idx.cpu().numpy(), bind_w=m.bind_w.cpu().numpy(),
            graph_idx=m.graph_idx.cpu().numpy() if m.graph_idx.shape[1] else None)
        gaussians = B.GaussianArrays(means=m.means.detach().cpu().numpy(),
                                     quats=quat_normalize(m.quats.detach()).cpu().numpy(),
                                     log_scales=m.log_scales.detach().cpu().numpy(),
                                     opacity_logits=m.opacity_logits.detach().cpu().numpy(),
                                     sh=m.sh().detach().cpu().numpy())
        frames = d.frame_numbers if d.frame_numbers is not None else torch.arange(d.num_frames)
        cams = [{"frame": int(frames[i]), "w2c": d.w2c[i].cpu().numpy(), "K": d.K[i].cpu().numpy(),
                 "width": d.width, "height": d.height, "time": float(d.times[i]),
                 "split": "val" if i in set(d.val_idx.tolist()) else "train",
                 "clip_index": int(d.clip_index[i]) if d.clip_index is not None else i} for i in range(d.num_frames)]
        scene = B.new_scene(int(frames.min()), int(frames.max()), d.fps, cams, config=self.cfg.to_dict(),
                            stats={"steps": self.step, "gaussians": m.num_gaussians, "nodes": m.num_nodes,
                                   "train_seconds": round(self.train_seconds, 2),
                                   "history": self.history, **(metrics or {})},
                            extent=d.extent, **self.scene_extra)
        return B.save_bundle(self.out_dir, scene, nodes, gaussians)

    def run(self) -> dict:
        """Train, evaluate on held-out frames, write the bundle; return a summary."""
        self.reporter.log(f"training {self.model.num_gaussians} Gaussians, {self.model.num_nodes} nodes, "
                          f"{self.cfg.steps} steps ({self.cfg.preset})")
        # the Numba kernels load (or, on a first run, compile) as their own progress stage,
        # not inside the first render below
        warm_kernels(self.reporter, self.device, self.cfg.backend)
        # held-out quality of the initialisation, so every run reports its own gain
        initial = self.evaluate() if self.step == 0 else self.initial_eval
        self.initial_eval = initial
        self.train()
        metrics = {"eval_init": initial, "eval": self.evaluate(), "eval_train": self.evaluate(self._train_sample())}
        metrics["iterations_per_s"] = round(self.step / max(self.train_seconds, 1e-9), 3)
        if self.still_plate is not None:
            metrics["still_plate"] = self.still_plate
        self._log_quality(metrics)
        path = self.export_bundle(metrics)
        CK.discard(self.ckpt_path)  # finished: a later --resume must not retrain over the bundle
        return {"bundle": str(path), "steps": self.step, "gaussians": self.model.num_gaussians,
                "nodes": self.model.num_nodes, **metrics}
