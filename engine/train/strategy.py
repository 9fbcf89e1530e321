"""Densification as strategy objects, in the manner of gsplat's ``Strategy``.

Each strategy holds its own state and is called by :class:`engine.train.trainer.Trainer`
at fixed points of a step; the trainer owns the model and the optimiser and passes them
in. :class:`GaussianDensifyStrategy` gathers screen-space gradient statistics after each
optimiser step and clones / splits / prunes Gaussians every ``densify_every`` steps;
:class:`NodeDensifyStrategy` then adds nodes where Gaussians are far from every node and
drops nodes nobody uses. Both edit parameters and Adam moments together
(:func:`engine.train.param_edit.edit_rows`).
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from ..geometry.quaternion import quat_apply, quat_identity, quat_normalize, quat_to_matrix
from .config import TrainConfig
from .data import TrainingData
from .init_model import trajectory_fg_score
from .lifespan import gaussian_budget
from .model import DynamicScene
from .param_edit import GAUSSIAN_BUFFERS, GAUSSIAN_PARAMS, NODE_PARAMS, edit_rows
from .split import graph_within_class


class GaussianDensifyStrategy:
    """Adaptive density control of the Gaussians (3DGS): clone, split, prune.

    When it runs: :meth:`step_post_backward` after every optimiser step (it only counts
    steps in ``[densify_from, densify_until)``); :meth:`densify` every ``densify_every``
    steps in that window; :meth:`reset_opacity` every ``opacity_reset_every`` steps before
    ``densify_until``.

    What it changes: its own statistics ``grad_accum [G]`` (summed view-space gradient
    norm, in NDC-like units) and ``grad_count [G]`` (steps in which the Gaussian was
    visible); in :meth:`densify` the model's per-Gaussian parameters, ``gauss_dyn [G]`` and
    their Adam moments; in :meth:`reset_opacity` the opacities and their moments.

    Parameters
    ----------
    cfg : TrainConfig
        ``densify_*``, ``percent_dense``, ``max_gaussians``, ``opacity_prune``.
    device : torch.device
        Where the statistics live (the training data's device).
    train_frames : int
        Training frames of the run (the moving seeds of a long clip with lifespans, and with
        them the budget, grow with it: :func:`~engine.train.lifespan.gaussian_budget`).
    """

    def __init__(self, cfg: TrainConfig, device, train_frames: int = 0):
        self.cfg = cfg
        self.device = device
        self.train_frames = int(train_frames)
        self.grad_accum: torch.Tensor | None = None
        self.grad_count: torch.Tensor | None = None

    def reset_stats(self, num_gaussians: int) -> None:
        """Zero the statistics for ``num_gaussians`` Gaussians."""
        g = num_gaussians
        self.grad_accum = torch.zeros(g, device=self.device)
        self.grad_count = torch.zeros(g, device=self.device)

    def state_dict(self) -> dict:
        """The statistics for a checkpoint: ``{"grad_accum": [G], "grad_count": [G]}`` on the CPU."""
        return {"grad_accum": self.grad_accum.cpu(), "grad_count": self.grad_count.cpu()}

    def load_state_dict(self, state: dict) -> None:
        """Take the statistics from a checkpoint (:meth:`state_dict`'s keys; others ignored)."""
        self.grad_accum = state["grad_accum"].to(self.device)
        self.grad_count = state["grad_count"].to(self.device)

    @torch.no_grad()
    def step_post_backward(self, step: int, out, width: int, height: int,
                           index: torch.Tensor | None = None) -> None:
        """Add this step's view-space gradient norms.

        Parameters
        ----------
        step : int
            The step that just ran (before the trainer increments it).
        out : RenderOutput
            The step's render: ``grad2d()`` [G, 2] pixel gradients of the means (None where
            the backend keeps none) and ``radii`` (> 0: visible).
        index : [L] long, optional
            The model rows ``out`` rendered (then its ``radii`` / pixel gradients are ``[L]``);
            the rows left out were not visible.
        """
        cfg = self.cfg
        grad2d = out.grad2d()
        if grad2d is not None and cfg.densify_from <= step < cfg.densify_until:
            vis = out.radii.reshape(-1) > 0
            gn = grad2d.norm(dim=-1)
            # gradient in NDC-like units: scale pixel gradients by half the image size
            gn = gn * 0.5 * max(width, height)
            # dense updates instead of boolean-mask gather/scatter, same values:
            # invisible Gaussians add exactly 0
            if index is None:
                self.grad_accum += torch.where(vis, gn, 0.0)
                self.grad_count += vis
            else:
                self.grad_accum.index_add_(0, index, torch.where(vis, gn, 0.0))
                self.grad_count.index_add_(0, index, vis.to(self.grad_count.dtype))

    @torch.no_grad()
    def densify(self, model: DynamicScene, opt: torch.optim.Adam, gen: torch.Generator) -> None:
        """Clone small hot Gaussians, split big ones, prune transparent ones.

        A Gaussian is hot when its mean gradient reaches ``densify_grad_threshold`` and big
        when its largest scale exceeds ``percent_dense`` of the scene extent. At most
        ``budget - G`` are added (the hottest first): ``max_gaussians`` plus the extra moving
        seeds of a run with lifespans (:func:`~engine.train.lifespan.gaussian_budget`). A split
        draws its copy's offset from the Gaussian (``gen``) and shrinks both by 1.6; the copies
        are appended after the kept rows and inherit their source's per-Gaussian buffers
        (``gauss_dyn``, the lifespan: :data:`GAUSSIAN_BUFFERS`). The statistics are not reset
        here (the trainer does, after node densification).
        """
        cfg, m = self.cfg, model
        grads = self.grad_accum / self.grad_count.clamp_min(1)
        scales = m.scales().max(dim=1).values
        big = scales > cfg.percent_dense * m.extent
        hot = grads >= cfg.densify_grad_threshold
        room = max(gaussian_budget(cfg, m, self.train_frames) - m.num_gaussians, 0)
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
            noise = torch.randn(std.shape, generator=gen).to(std) * std
            rot = quat_to_matrix(quat_normalize(m.quats[split]))
            offset = torch.zeros(len(src), 3, device=self.device)
            offset[len(clone):] = (rot @ noise.unsqueeze(-1)).squeeze(-1)
            extra = {name: getattr(m, name).detach()[src].clone() for name in GAUSSIAN_PARAMS}
            extra["means"] = extra["means"] + offset
            extra["log_scales"][len(clone):] -= math.log(1.6)
            # the split originals shrink too
            m.log_scales.data[split] -= math.log(1.6)
        keep = m.opacities() > cfg.opacity_prune
        # per-Gaussian buffers follow their rows: kept ones, then the copies' sources; the
        # binding too, so that the rows still have theirs until the trainer rebinds (a row
        # held in its seed frame reaches canonical space through it, seed_anchor.py)
        rows = {name: getattr(m, name)[keep] for name in GAUSSIAN_BUFFERS + ("bind_idx", "bind_w")}
        if extra:
            rows = {name: torch.cat([v, getattr(m, name)[src]]) for name, v in rows.items()}
        edit_rows(m, opt, keep, extra or None)
        for name, value in rows.items():
            setattr(m, name, value.contiguous())

    @staticmethod
    def reset_opacity(model: DynamicScene, opt: torch.optim.Adam) -> None:
        """Clamp every opacity to at most 0.01 and zero the opacity moments."""
        with torch.no_grad():
            model.opacity_logits.data.clamp_(max=math.log(0.01 / 0.99))
        for group in opt.param_groups:
            if group["name"] == "opacity_logits":
                st = opt.state.get(group["params"][0])
                if st:
                    st["exp_avg"].zero_()
                    st["exp_avg_sq"].zero_()


class NodeDensifyStrategy:
    """Node densification: add nodes where Gaussians are far from every node; drop nodes
    nobody uses.

    When it runs: right after each Gaussian densification (:meth:`densify`, with
    ``cfg.node_densify``), once the Gaussians have been rebound.

    What it changes: the model's per-node tensors (``pos_keys [N, K, 3]`` / ``rot_keys
    [N, K, 4]`` with their Adam moments, ``node_log_radii``, ``node_centers``,
    ``node_p_dyn``, ``node_fg``, ``node_dyn`` [N]), the node graph ``graph_idx [N, k]``,
    and the static-motion reference it is given; then it rebinds (the ``rebind`` callback,
    which also rebinds the lifted track points). It holds no state between calls.

    Parameters
    ----------
    cfg : TrainConfig
        ``node_prune_weight``, ``node_spawn_factor``, ``node_add_max``,
        ``max_nodes_factor``, ``num_nodes``, ``seed``.
    data : TrainingData
        Its ``fg`` prior decides whether a spawned node moves (:meth:`spawn_motion`).
    device : torch.device
    """

    def __init__(self, cfg: TrainConfig, data: TrainingData, device):
        self.cfg = cfg
        self.data = data
        self.device = device

    def densify(self, model: DynamicScene, opt: torch.optim.Adam, static_ref, rebind: Callable[[], None]):
        """Spawn and prune nodes; returns the static-motion reference, edited alike.

        A Gaussian farther than ``node_spawn_factor`` times its nearest node's radius is
        poorly controlled. Up to ``node_add_max`` such Gaussians (farthest-point spread)
        become new nodes that start with their parent node's motion, shifted to their
        position; nodes whose summed binding weight is ~0 are removed. The graph and the
        binding are rebuilt afterwards.

        Parameters
        ----------
        static_ref : (pos [N, K, 3], rot [N, K, 4]) or None
            The initial keys (``loss.static_init``); spawned nodes get their starting keys.
        rebind : callable
            Rebinds the Gaussians (and track points) to the new nodes.

        Returns
        -------
        (pos [N', K, 3], rot [N', K, 4]) or None
        """
        from ..nodes.baselines import farthest_point_sampling
        from ..nodes.graph import node_graph

        cfg, m = self.cfg, model
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
                    follow, spawn_fg = self.spawn_motion(m, par, new_c)
                if m.pos_keys is not None:
                    # a following node starts with exactly its parent's rigid motion: at each
                    # key p_new = p_par + R_par (c_new − c_par) (without R_par the Gaussians
                    # it takes over would jump by (I − R_par)(c_new − c_par)); a static one
                    # stays at c_new with the identity rotation
                    rk = m.rot_keys[par].detach()
                    shift = (new_c - m.node_centers[par]).unsqueeze(1).expand(-1, rk.shape[1], -1)
                    keys = m.pos_keys[par].detach() + quat_apply(quat_normalize(rk), shift)
                    ident = quat_identity(*rk.shape[:-1], dtype=rk.dtype, device=rk.device)
                    fol = follow[:, None, None]
                    extra["pos_keys"] = torch.where(fol, keys, new_c.unsqueeze(1).expand_as(keys))
                    extra["rot_keys"] = torch.where(fol, rk, ident)
                new_centers = torch.cat([m.node_centers[keep], new_c])
                new_pdyn = torch.cat([m.node_p_dyn[keep], m.node_p_dyn[par]])
                new_fg = torch.cat([m.node_fg[keep], spawn_fg])
                new_dyn = torch.cat([m.node_dyn[keep], follow if m.is_split else torch.ones_like(follow)])
            elif bool(keep.all()):
                return static_ref
            else:
                new_centers, new_pdyn, new_fg = m.node_centers[keep], m.node_p_dyn[keep], m.node_fg[keep]
                new_dyn = m.node_dyn[keep]
            if static_ref is not None:  # spawned nodes: their starting keys are their reference
                ref_p, ref_q = static_ref[0][keep], static_ref[1][keep]
                if extra is not None and "pos_keys" in extra:
                    ref_p = torch.cat([ref_p, extra["pos_keys"]])
                    ref_q = torch.cat([ref_q, extra["rot_keys"]])
                static_ref = (ref_p.contiguous(), ref_q.contiguous())
            edit_rows(m, opt, keep, extra, names=NODE_PARAMS)
            radii = m.node_log_radii[keep]
            m.node_log_radii = (radii if extra is None else torch.cat([radii, extra["node_log_radii"]])).contiguous()
            m.node_centers = new_centers.contiguous()
            m.node_p_dyn = new_pdyn.contiguous()
            m.node_fg = new_fg.contiguous()
            m.node_dyn = new_dyn.contiguous()
            k = m.graph_idx.shape[1] if m.graph_idx.numel() else 0
            paths = m.pos_keys if cfg.arap_graph == "paths" else None
            if k and (m.is_split or paths is not None):
                m.graph_idx = graph_within_class(new_centers, m.node_dyn, k, paths=paths)  # one class unsplit
            elif k:
                m.graph_idx = node_graph(new_centers.cpu(), k)[0].to(self.device)
            rebind()
        return static_ref

    def spawn_motion(self, model: DynamicScene, par: torch.Tensor, new_c: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
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
        m, d = model, self.data
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
