"""The training objective: the loss terms of one step and the supervision they need.

:class:`Objective` assembles the weighted loss of one rendered frame (photometric at full and
at coarse resolution, depth, mask, track, dynamic Gaussians on the moving region, ARAP,
static motion, spline smoothness) from the
model, the training data and ``cfg.loss``. It owns the state those terms carry across steps:
the lifted 2D tracks (:meth:`Objective.prepare_tracks`, rebound with the Gaussians by
:meth:`Objective.rebind_tracks`), the static-motion reference ``static_ref`` and the moving
regions' distance maps ``mask_dist``.
"""

from __future__ import annotations

import torch

from ..geometry.camera import unproject
from ..geometry.quaternion import quat_normalize
from . import losses as L
from .config import TrainConfig
from .data import TrainingData
from .fused_reg import fused_arap, fused_key_terms, fused_reg_available
from .init_model import canonicalise
from .model import DynamicScene
from .terms import depth_term, image_l1_terms, on_mask_term, track_term

#: ARAP / static-motion / smoothness through engine/train/fused_reg.py on the CPU (tests
#: switch it off to compare with the torch versions)
FUSED_REG = True


class Objective:
    """The loss of one training step, and the state its terms keep.

    Parameters
    ----------
    data : TrainingData
    cfg : TrainConfig
        ``cfg.loss`` weights the terms; ``warmup_static_steps`` holds motion terms back.
    gen : torch.Generator
        The run's CPU generator (track subsampling, ARAP's second time), shared with the
        trainer so the draws keep their order.

    Attributes
    ----------
    track_canon : [P, 3] tensor or None
        Lifted track points in canonical space (None: no track term); with ``track_ids
        [P]`` (rows of ``data.tracks_xy``), ``track_idx [P, k]`` / ``track_w [P, k]`` (their
        binding) and ``track_vis [T, F]`` (visibility without the held-out frames).
    static_ref : (pos [N, K, 3], rot [N, K, 4]) or None
        Initial keys of every node, the static-motion reference (``loss.static_init > 0``).
    mask_dist : [F, H, W] tensor or None
        Distance in px to each frame's nearest moving pixel (:func:`~engine.train.losses.mask_distance`),
        for the on-mask term; derived from the dynamic prior on first use.
    """

    def __init__(self, data: TrainingData, cfg: TrainConfig, gen: torch.Generator):
        self.data = data
        self.cfg = cfg
        self.gen = gen
        self.track_canon = None
        # initial keys of every node [N, K, 3] / [N, K, 4] (spline / per-frame motion): the
        # reference of the static-motion term; kept only when loss.static_init > 0
        self.static_ref = None
        self.mask_dist = None  # [F, H, W] px to the nearest moving pixel (on_mask term), made on first use

    # ---------------------------------------------------------------- track supervision
    def prepare_tracks(self, model: DynamicScene) -> None:
        """Lift each track once (first visible frame, at its own depth there where it has one,
        else the depth prior's) and map it to canonical space."""
        d = self.data
        if d.tracks_xy is None or d.depth is None or self.cfg.loss.track == 0 or model.mlp is not None:
            return
        vis = d.tracks_vis.clone()
        vis[:, d.val_idx] = False  # never supervise with held-out frames
        has = vis.any(1)
        if model.is_split and d.fg is not None:
            # static tracks would only pull on frozen static nodes: supervise the moving ones
            has &= self.moving_tracks(vis)
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
        if d.tracks_depth is not None:
            # a track with a depth of its own (along a hinge's rings: the prior sees the
            # background behind a thin moving link) is lifted there, as the node paths were
            own = d.tracks_depth[pid, f0]
            z = torch.where(torch.isfinite(own) & (own > 0), own, z)
        ok = z > 0
        pid, f0, uv, z = pid[ok], f0[ok], uv[ok], z[ok]
        m = model
        x = unproject(d.K[f0], d.w2c[f0], uv, z)
        # with the split, mapped and bound through the dynamic nodes only (moving tracks)
        dyn = torch.nonzero(m.node_dyn).squeeze(1) if m.is_split else None
        canon = canonicalise(m, x, d.times[f0].to(x.dtype), dyn, m.bind_k)
        idx, wts = m.bind_points(canon)
        self.track_ids, self.track_canon, self.track_idx, self.track_w = pid, canon, idx, wts
        self.track_vis = vis

    def moving_tracks(self, vis: torch.Tensor) -> torch.Tensor:
        """``[P] bool``: tracks whose median dynamic prior over their visible frames reaches
        ``cfg.dynamic_threshold``."""
        from ..priors.dynamic_depth import moving_tracks

        d = self.data
        return torch.as_tensor(moving_tracks(d.tracks_xy.cpu().numpy(), vis.cpu().numpy(), d.fg.cpu().numpy(),
                                             self.cfg.dynamic_threshold), device=vis.device)

    def rebind_tracks(self, model: DynamicScene) -> None:
        """Bind the lifted track points to the model's current nodes (after the Gaussians)."""
        if self.track_canon is not None:
            with torch.no_grad():
                idx, w = model.bind_points(self.track_canon)
            self.track_idx, self.track_w = idx, w.to(self.track_w.dtype)

    def state_dict(self) -> dict:
        """What a checkpoint keeps: ``{"tracks": {ids, canon, idx, w, vis} or None,
        "static_ref": [pos, rot] or None}``, on the CPU."""
        return {
            # lifted track anchors are computed once from the initial model; a resumed
            # run must reuse them to reproduce the uninterrupted run
            "tracks": None if self.track_canon is None else {
                "ids": self.track_ids.cpu(), "canon": self.track_canon.cpu(), "idx": self.track_idx.cpu(),
                "w": self.track_w.cpu(), "vis": self.track_vis.cpu()},
            "static_ref": None if self.static_ref is None else [x.cpu() for x in self.static_ref],
        }

    def load_state_dict(self, state: dict, device) -> None:
        """Take the tracks and the static-motion reference from a checkpoint onto ``device``."""
        ref = state.get("static_ref")  # absent in checkpoints from before static_init
        keep_ref = ref is not None and self.cfg.loss.static_init > 0
        self.static_ref = tuple(x.to(device) for x in ref) if keep_ref else None
        tracks = state.get("tracks")
        if tracks is not None:
            dev = device
            self.track_ids, self.track_canon = tracks["ids"].to(dev), tracks["canon"].to(dev)
            self.track_idx, self.track_w = tracks["idx"].to(dev), tracks["w"].to(dev)
            self.track_vis = tracks["vis"].to(dev)

    # ---------------------------------------------------------------- the loss
    def terms(self, model: DynamicScene, step: int, f: int, t: float, out, means_t: torch.Tensor,
              quats_t: torch.Tensor, nodes_t, shown: torch.Tensor | None = None, deform=None):
        """The loss terms of frame ``f`` at training step ``step``: ``(loss, metrics, out)``.

        ``out`` is the frame's render (its ``extra`` channel the dynamic score on a mask
        step), ``means_t [G, 3]`` / ``quats_t [G, 4]`` the deformed Gaussians, ``nodes_t`` =
        node positions [N, 3], rotations [N, 4] and dual quaternions [N, 8] at ``t``
        (computed once by the trainer's ``_loss``). ``shown [L]``: the rows of the model that
        ``means_t`` / ``quats_t`` are (``[L, ...]``; None = every Gaussian). ``deform(t, dq_nodes,
        index)``: how the step moves other rows, default ``model.deform`` (the trainer passes the
        seed-frame deformation of ``engine/train/seed_anchor.py`` while it holds rows there).
        """
        d, m, w = self.data, model, self.cfg.loss
        pos_t, rot_t, dq_nodes = nodes_t
        target = d.images[f]
        weight = None
        if w.rgb_dynamic > 0 and d.fg is not None:
            # moving pixels are a few % of the image: weight them up so the objects get a
            # share of the photometric gradient that is not drowned by the background
            weight = (1.0 + w.rgb_dynamic * (d.fg[f] >= self.cfg.dynamic_threshold).to(target.dtype)).unsqueeze(-1)
        # L1, the coarse L1 and the PSNR's squared error in one pass (L.photometric's L1 part)
        l1, coarse, mse = image_l1_terms(out.rgb, target, weight, L.COARSE_POOLS if w.rgb_coarse > 0 else ())
        terms = {"rgb": L.photometric(out.rgb, target, w.ssim, weight, l1_value=l1) * w.rgb}
        if w.rgb_coarse > 0:
            terms["rgb_coarse"] = w.rgb_coarse * coarse
        if w.depth > 0 and d.depth is not None:
            terms["depth"] = w.depth * depth_term(out.depth[..., 0], out.alpha[..., 0], d.depth[f])
        if out.extra is not None:  # a mask step (see the trainer's _loss)
            terms["mask"] = w.mask * L.mask_loss(out.alpha, out.extra, d.fg[f])
        if self.track_canon is not None and w.track > 0 and step >= self.cfg.warmup_static_steps:
            track = self.track_terms(m, f, t, dq_nodes)
            if track is not None:
                terms["track"] = w.track * track
        if w.on_mask > 0 and step >= self.cfg.warmup_static_steps:
            on_mask = self.on_mask(m, f, t, means_t, dq_nodes, shown, deform)
            if on_mask is not None:
                terms["on_mask"] = w.on_mask * on_mask
        motion_on = step >= self.cfg.warmup_static_steps
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
            st, vel, acc = fused_key_terms(m.pos_keys, m.rot_keys, m.key_times, *self.static_weights(m), m.extent,
                                           *self.static_reference())
            smooth = (vel, acc)
        else:
            st = self.static_motion(m, pos_t, rot_t, state_t1) if static_on else None
            smooth = L.spline_smoothness(m.pos_keys / m.extent, m.key_times) if smooth_on else None
        if smooth_on:
            terms["velocity"] = w.velocity * smooth[0]
            terms["acceleration"] = w.acceleration * smooth[1]
        if static_on:
            terms["static"] = w.static * st
        loss = sum(terms.values())
        with torch.no_grad():
            metrics = {k: float(v) for k, v in terms.items()}
            metrics["psnr"] = float(L.psnr_from_mse(mse))  # L.psnr of the clamped render
        return loss, metrics, out

    # ---------------------------------------------------------------- tracks over the clip
    def track_terms(self, model: DynamicScene, f: int, t: float, dq_nodes: torch.Tensor) -> torch.Tensor | None:
        """The track term (unweighted) of frame ``f`` (time ``t``, node transforms ``dq_nodes [N, 8]``)
        plus that of ``cfg.track_frames - 1`` training frames drawn with the run's generator, summed;
        None where none of them sees a supervised track.

        Why the other frames: a step renders one frame, and its photometric gradient moves only the
        spline keys near that frame's time, so over the run each key random-walks by about the step
        size (docs/benchmarks.md "What caps the moving regions near 20 dB"). The tracks at a few other
        times each step hold the rest of every path (docs/benchmarks.md "Tracks at other times").
        Each other frame costs one node-state evaluation and the deformation of up to 1024 track
        points.
        """
        d = self.data
        frames = [(f, t, dq_nodes)]
        if self.cfg.track_frames > 1:
            tr = d.train_idx
            draw = torch.randint(len(tr), (self.cfg.track_frames - 1,), generator=self.gen)
            for g in tr[draw.to(tr.device)].tolist():
                tg = float(d.times[g])
                frames.append((g, tg, None))
        total = None
        for g, tg, dq in frames:
            sel = torch.nonzero(self.track_vis[self.track_ids, g]).squeeze(1)
            if len(sel) == 0:
                continue
            if len(sel) > 1024:
                sel = sel[torch.randperm(len(sel), generator=self.gen)[:1024].to(sel.device)]
            if dq is None:
                dq = model.node_state_dq(tg)[2]
            x = model.deform_points(self.track_canon[sel], self.track_idx[sel], self.track_w[sel], tg, dq_nodes=dq)
            # in % of the image width (Huber, linear beyond 0.05 %): at the width of the
            # image the term vanished next to the photometric one (a 10 px error cost 1e-4)
            term = track_term(x, d.K[g], d.w2c[g], d.tracks_xy[self.track_ids[sel], g], float(d.width) / 100.0)
            total = term if total is None else total + term
        return total

    # ---------------------------------------------------------------- dynamic Gaussians on the mask
    def on_mask(self, model: DynamicScene, f: int, t: float, means_t: torch.Tensor, dq_nodes: torch.Tensor,
                shown: torch.Tensor | None = None, deform=None) -> torch.Tensor | None:
        """How far the dynamic Gaussians of frame ``f`` project outside its moving region
        (:func:`~engine.train.losses.on_mask_loss` of up to 4096 of them, drawn with the run's
        generator), or None (no split, no dynamic prior, no moving pixel in the frame).

        Why: a node's initial trajectory follows its tracks only while they live (about two
        frames on fast parts) and rests outside them, so each stretch of time gets its own
        Gaussians for the same moving object, right near their seeding frame and left behind
        or drifting elsewhere (on the generated large-motion scene only 3-30 % of the Gaussians
        on an object at the middle frame are still on it at the ends). Rendered there they
        are floaters or hidden under the floor, where the photometric and mask terms cannot
        reach them; the distance map pulls them back onto the moving pixels of every frame from
        as far away as they are. ``means_t [G, 3]``: the deformed centres at frame ``f`` (time
        ``t``, node transforms ``dq_nodes [N, 8]``); with ``shown [L]`` they are only those rows
        (``[L, 3]``), and the drawn Gaussians are deformed here, shown or not (the pull is on
        every dynamic Gaussian, inside its lifespan window or not, as without the cull), by
        ``deform(t, dq_nodes, index)`` (default ``model.deform``).
        """
        d, m = self.data, model
        if not m.is_split or d.fg is None:
            return None
        if self.mask_dist is None:
            self.mask_dist = L.mask_distance(d.fg, self.cfg.dynamic_threshold)
            # frames with a pull somewhere (all 0: nothing moving, or everything), once per run
            self._mask_pulls = (self.mask_dist.flatten(1) > 0).any(1).tolist()
        if not self._mask_pulls[f]:
            return None
        dyn = torch.nonzero(m.gauss_dyn).squeeze(1)
        if len(dyn) == 0:
            return None
        if len(dyn) > 4096:
            dyn = dyn[torch.randperm(len(dyn), generator=self.gen)[:4096].to(dyn.device)]
        if shown is None:
            centres = torch.index_select(means_t, 0, dyn)
        elif deform is not None:
            centres = deform(t, dq_nodes, dyn)[0]
        else:
            centres = m.deform(t, dq_nodes=dq_nodes, index=dyn)[0]
        return on_mask_term(centres, d.K[f], d.w2c[f], self.mask_dist[f], float(d.width) / 100.0)

    # ---------------------------------------------------------------- static motion
    def static_motion(self, model: DynamicScene, pos_t: torch.Tensor, rot_t: torch.Tensor,
                      state_t1=None) -> torch.Tensor:
        """Motion of the nodes the prior calls static: ``mean_i (1 − s_i) e_i`` with ``s_i`` the
        node's foreground score (:func:`node_fg_score`, the same for every initialiser).

        ``e_i`` is the variance over time of the node's position and rotation, in units of
        the scene extent, so a constant trajectory (any fixed offset) costs nothing. Keyed
        motion (spline, per_frame) computes it exactly over its keys; the MLP estimates it
        without bias from this step's time ``t`` (``pos_t [N, 3]``, ``rot_t [N, 4]``) and a
        second random time ``t1`` (``state_t1`` = positions and rotations there) as
        ``½|x(t) − x(t1)|²`` (``E|x(t) − x(t1)|² = 2 Var x``). Rotation is measured as the
        displacement it causes at the node's radius (``2ρ|Δq|``), so a large static node
        pays for turning the Gaussians far from its centre. With ``loss.static_init = a >
        0`` keyed motion is measured relative to ``a`` times the node's initial keys
        (:attr:`static_ref`).
        """
        m = model
        s, arm = self.static_weights(m)
        if m.pos_keys is not None:
            return L.static_motion_keys(m.pos_keys, m.rot_keys, s, arm, m.extent, *self.static_reference())
        pos_1, rot_1 = state_t1
        e = 0.5 * ((((pos_t - pos_1) / m.extent) ** 2).sum(-1) + ((rot_t - rot_1) ** 2).sum(-1) * arm)
        return (s * e).mean()  # a mean over nodes, like ARAP and smoothness

    def static_weights(self, model: DynamicScene) -> tuple[torch.Tensor, torch.Tensor]:
        """The static-motion term's per-node weight ``(1 − fg)^power`` and rotation arm
        ``(2ρ / extent)²``, both [N] constants."""
        m = model
        s = (1.0 - m.node_fg).clamp(0, 1) ** self.cfg.loss.static_power
        if m.is_split:  # a dynamic node is never held still; static ones are frozen anyway
            s = torch.where(m.node_dyn, torch.zeros_like(s), s)
        arm = (2.0 * m.node_radii().detach() / m.extent) ** 2
        return s, arm

    def static_reference(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """``(a · initial pos keys, a · normalised initial rot keys)`` with ``a =
        loss.static_init``, or ``(None, None)``: motion beyond the initial trajectory, so a
        node on a thin moving part that the prior half-calls static keeps the motion its
        tracks gave it."""
        if self.static_ref is None:
            return None, None
        a = self.cfg.loss.static_init
        return a * self.static_ref[0], a * quat_normalize(self.static_ref[1])

    def dynamic_score(self, model: DynamicScene) -> torch.Tensor:
        """Per-Gaussian dynamic score [G] for the mask term (the colour pass's extra
        channel): the Gaussian's class with the split, else the bound nodes' ``p_dyn``
        blended by the binding weights. It changes only
        when the binding or the nodes do (rebind / densification assign new tensors), so it
        is cached on the identity and version of its inputs."""
        m = model
        if m.is_split:  # the class itself: dynamic Gaussians should cover the moving pixels
            key, score = (m.gauss_dyn,), lambda: m.gauss_dyn.to(m.means.dtype)
        else:
            key, score = (m.bind_idx, m.bind_w, m.node_p_dyn), lambda: (m.node_p_dyn[m.bind_idx] * m.bind_w).sum(-1)
        versions = tuple(x._version for x in key)
        c = getattr(self, "_dyn_cache", None)
        if c is None or len(c[0]) != len(key) or any(a is not b for a, b in zip(c[0], key)) or c[1] != versions:
            self._dyn_cache = c = (key, versions, score().contiguous())
        return c[2]
