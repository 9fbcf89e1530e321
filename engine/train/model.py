"""The dynamic scene model: canonical Gaussians driven by spline-parameterised nodes.

A Gaussian ``g`` with canonical centre ``x_g`` and rotation ``q_g`` is moved at time
``t`` by dual-quaternion blending of the transforms of its ``K_b`` bound nodes
(paper Sec. 'Node-Based Deformation Representation')::

    T_i(t) x = R(q_i(t)) (x − c_i) + p_i(t)          node transform (docs/architecture.md)
    Q_g(t)   = normalise(Σ_i w_gi DQ(T_i(t)))         dual-quaternion blend
    x_g(t)   = Q_g(t) · x_g,   q_g(t) = rot(Q_g(t)) ⊗ q_g

Node motion comes from one of three models (``TrainConfig.motion``):

``spline``     cubic Hermite keys (positions and quaternions) with Catmull-Rom tangents;
               the paper's model.
``per_frame``  one key per training frame (the same spline machinery, no smoothing).
``mlp``        an SC-GS-style deformation MLP ``(c_i, t) -> (Δp, Δq)``, the baseline the
               paper improves on.
"""

from __future__ import annotations

import numpy as np

import torch
import torch.nn as nn

from ..geometry.binding import bind_gaussians
from ..geometry.dualquat import dq_apply_points, dq_apply_rotations, dq_blend, node_transforms_dq
from ..geometry.hermite import catmull_rom_basis, catmull_rom_tangents, hermite_eval, hermite_eval_quat
from ..geometry.quaternion import quat_identity, quat_normalize
from .fused import fused_available, fused_deform
from .fused_nodes import fused_node_state
from .lifespan import lifespan_window
from .motion_mlp import DeformMLP, positional_encoding  # noqa: F401 (re-exported)
from .split import bind_within_class, knn_rbf, resting_nodes

# Use the fused CPU deformation (engine/train/fused.py) where it applies; the torch
# path (gaussian_transforms + dq_apply_*) is the reference and the GPU path.
FUSED_DEFORM = True
#: node splines and transforms through engine/train/fused_nodes.py on the CPU (tests switch
#: it off to compare with the torch ops)
FUSED_NODES = True

SH_C0 = 0.28209479177387814


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


class DynamicScene(nn.Module):
    """Canonical Gaussians + nodes + node motion.

    Parameters (all ``nn.Parameter``)
    ---------------------------------
    means [G, 3], quats [G, 4] (wxyz, unnormalised), log_scales [G, 3],
    opacity_logits [G], sh_dc [G, 1, 3], sh_rest [G, M-1, 3];
    spline/per_frame: pos_keys [N, K, 3], rot_keys [N, K, 4].

    Buffers
    -------
    node_centers [N, 3] canonical node centres ``c_i``; node_log_radii [N] (the RBF radius
    ``ρ_i`` of the binding weights, from the initialiser's node spacing: a constant, since the
    weights are recomputed under no_grad at each rebind, a learned radius would get no
    gradient); key_times [K];
    bind_idx [G, K_b], bind_w [G, K_b]; graph_idx [N, k]; node_p_dyn [N]; node_fg [N];
    node_dyn [N] bool, gauss_dyn [G] bool: the static / dynamic split
    (``engine/train/split.py``; all True = one class, the model before the split);
    gauss_t_center [G], gauss_lifespan [G]: each Gaussian's lifespan as seeded, in engine
    time (:meth:`opacities_at`; lifespan 0 = always visible, the default).
    gauss_view_origin [G, 3], gauss_view_angle [G]: a view-bound Gaussian's seed camera centre
    and the parallax angle scale its opacity fades over away from that camera
    (``engine/train/shot_detail.py``; angle 0 = seen alike from everywhere, the default).

    Parameters (per Gaussian, besides appearance and geometry)
    ----------------------------------------------------------
    lifespan_log_scale [G]: log of the factor each Gaussian's lifespan has learned over its
    seeded one (:meth:`lifespans`; 0 = as seeded; the trainer keeps it inside
    ``TrainConfig.lifespan_min`` .. ``lifespan_max``, ``engine/train/lifespan.py``).
    """

    def __init__(self, means, colors, scales, opacities, node_centers, node_radii, key_times, pos_keys,
                 rot_keys=None, sh_degree: int = 1, motion: str = "spline", bind_k: int = 4, graph_idx=None,
                 node_p_dyn=None, extent: float = 1.0):
        super().__init__()
        g = means.shape[0]
        n, k = pos_keys.shape[:2]
        m = (sh_degree + 1) ** 2
        self.sh_degree = sh_degree
        self.motion = motion
        self.bind_k = min(bind_k, n)
        self.extent = float(extent)
        dev, dt = means.device, means.dtype
        self.means = nn.Parameter(means.clone())
        q = torch.zeros(g, 4, device=dev, dtype=dt)
        q[:, 0] = 1
        self.quats = nn.Parameter(q)
        self.log_scales = nn.Parameter(torch.log(scales.clamp_min(1e-7)).clone())
        self.opacity_logits = nn.Parameter(inverse_sigmoid(opacities).clone())
        self.sh_dc = nn.Parameter(((colors - 0.5) / SH_C0).view(g, 1, 3).clone())
        self.sh_rest = nn.Parameter(torch.zeros(g, m - 1, 3, device=dev, dtype=dt))
        self.register_buffer("node_log_radii", torch.log(node_radii.clamp_min(1e-6)).clone())
        self.register_buffer("node_centers", node_centers.clone())
        self.register_buffer("key_times", key_times.clone())
        self.register_buffer("node_p_dyn", node_p_dyn.clone() if node_p_dyn is not None else torch.zeros(n, device=dev))
        # per-node dynamic score from the foreground prior along the node's initial
        # trajectory, the same computation for every initialiser (Trainer.node_fg_score);
        # weights the static-motion regulariser by (1 - score)
        self.register_buffer("node_fg", torch.zeros(n, device=dev))
        self.register_buffer("graph_idx", graph_idx.clone() if graph_idx is not None
                             else torch.zeros(n, 0, dtype=torch.long, device=dev))
        if motion == "mlp":
            self.mlp = DeformMLP(extent).to(dev, dt)
            # The MLP moves nodes relative to their canonical centres; the spline init
            # (from tracks) is not used, as in SC-GS.
            self.pos_keys = None
            self.rot_keys = None
        else:
            self.mlp = None
            self.pos_keys = nn.Parameter(pos_keys.clone())
            if rot_keys is None:
                rot_keys = quat_identity(n, k, device=dev, dtype=dt)
            self.rot_keys = nn.Parameter(rot_keys.clone())
        self.register_buffer("node_dyn", torch.ones(n, dtype=torch.bool, device=dev))
        self.register_buffer("gauss_dyn", torch.ones(g, dtype=torch.bool, device=dev))
        self.register_buffer("gauss_t_center", torch.zeros(g, device=dev, dtype=dt))
        self.register_buffer("gauss_lifespan", torch.zeros(g, device=dev, dtype=dt))
        self.register_buffer("gauss_view_origin", torch.zeros(g, 3, device=dev, dtype=dt))
        self.register_buffer("gauss_view_angle", torch.zeros(g, device=dev, dtype=dt))
        self.lifespan_log_scale = nn.Parameter(torch.zeros(g, device=dev, dtype=dt))
        self.register_buffer("bind_idx", torch.zeros(g, self.bind_k, dtype=torch.long, device=dev))
        self.register_buffer("bind_w", torch.zeros(g, self.bind_k, device=dev, dtype=dt))
        self.rebind()

    # ------------------------------------------------------------------ sizes
    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_nodes(self) -> int:
        return int(self.node_centers.shape[0])

    # ------------------------------------------------------------------ appearance
    def scales(self, index: torch.Tensor | None = None) -> torch.Tensor:
        """Scales [G, 3] (``index [L]``: of those rows only, [L, 3])."""
        return torch.exp(self.log_scales if index is None else self.log_scales[index])

    def opacities(self, index: torch.Tensor | None = None) -> torch.Tensor:
        """Opacity [G] without lifespans (what densification prunes on; ``index [L]``: of those
        rows only)."""
        return torch.sigmoid(self.opacity_logits if index is None else self.opacity_logits[index])

    def lifespans(self, index: torch.Tensor | None = None) -> torch.Tensor:
        """Lifespan [G] in engine time: the seeded one times ``exp(lifespan_log_scale)`` (0 =
        always visible; ``index [L]``: of those rows only). What the bundle stores and the
        Blender preview windows by."""
        if index is None:
            return self.gauss_lifespan * torch.exp(self.lifespan_log_scale)
        return self.gauss_lifespan[index] * torch.exp(self.lifespan_log_scale[index])

    def opacities_at(self, t: float | None, index: torch.Tensor | None = None,
                     means: torch.Tensor | None = None, view_center: torch.Tensor | None = None) -> torch.Tensor:
        """Opacity [G] at engine time ``t``: :meth:`opacities` times each Gaussian's lifespan
        window ``exp(-0.5 ((t - t_center) / lifespan)^2)`` (:meth:`lifespans`; 1 where the
        lifespan is 0, and everywhere when ``t`` is None). ``index [L]``: of those rows only
        ([L]; the same values as the full tensor's rows). With ``means`` (the rows' deformed
        centres, ``[G, 3]`` or ``[L, 3]``) and ``view_center [3]`` (the camera centre), also the
        view-bound Gaussians' fade (:func:`engine.train.shot_detail.view_fade`)."""
        opacity = self.opacities(index)
        if t is not None and bool((self.gauss_lifespan > 0).any()):
            t_center = self.gauss_t_center if index is None else self.gauss_t_center[index]
            opacity = opacity * lifespan_window(float(t), t_center, self.lifespans(index))
        if means is not None and view_center is not None and bool((self.gauss_view_angle > 0).any()):
            from .shot_detail import view_fade  # here: shot_detail imports this module

            origin, angle = self.gauss_view_origin, self.gauss_view_angle
            if index is not None:
                origin, angle = origin[index], angle[index]
            opacity = opacity * view_fade(means.detach(), origin, angle, view_center)
        return opacity

    def sh(self, index: torch.Tensor | None = None) -> torch.Tensor:
        """[G, M, 3] spherical-harmonic coefficients (``index [L]``: of those rows only)."""
        if index is None:
            return torch.cat([self.sh_dc, self.sh_rest], dim=1)
        return torch.cat([self.sh_dc[index], self.sh_rest[index]], dim=1)

    def node_radii(self) -> torch.Tensor:
        return torch.exp(self.node_log_radii)

    # ------------------------------------------------------------------ motion
    @property
    def is_split(self) -> bool:
        """Whether the model has static nodes (``engine/train/split.py``)."""
        return not bool(self.node_dyn.all())

    @torch.no_grad()
    def bind_points(self, points: torch.Tensor, point_dyn: torch.Tensor | None = None):
        """K nearest nodes and RBF weights ``([P, K_b], [P, K_b])`` of canonical ``points
        [P, 3]``; with the split, among the nodes of each point's class (``point_dyn [P]``,
        default dynamic)."""
        radii = self.node_radii().detach()
        if not self.is_split:
            return bind_gaussians(points, self.node_centers, radii, self.bind_k)
        if point_dyn is None:
            point_dyn = torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
        return bind_within_class(points, point_dyn, self.node_centers, self.node_dyn, radii, self.bind_k,
                                 fused=FUSED_DEFORM)

    @torch.no_grad()
    def rebind(self) -> None:
        """Refresh each Gaussian's K nearest nodes and RBF weights (canonical space)."""
        points = self.means.detach()
        if self.is_split:
            idx, w = self.bind_points(points, self.gauss_dyn)
        else:
            idx, w = knn_rbf(points, self.node_centers, self.node_radii().detach(), self.bind_k, fused=FUSED_DEFORM)
        self.bind_idx = idx
        self.bind_w = w.to(self.means.dtype)

    def set_explicit_tangents(self, pos_out, rot_out, pos_in=None, rot_in=None) -> None:
        """Use these tangents (e.g. edited in Blender) instead of Catmull-Rom ones.

        Locks the trajectories: with explicit tangents the keys are buffers, not
        parameters, so appearance can be fine-tuned under a fixed, artist-edited motion.
        """
        self.explicit_tangents = {"pos_out": pos_out, "rot_out": rot_out,
                                  "pos_in": pos_out if pos_in is None else pos_in,
                                  "rot_in": rot_out if rot_in is None else rot_in}
        self.pos_keys.requires_grad_(False)
        self.rot_keys.requires_grad_(False)

    def node_tangents(self) -> tuple[torch.Tensor, torch.Tensor]:
        explicit = getattr(self, "explicit_tangents", None)
        if explicit is not None:
            return explicit["pos_out"], explicit["rot_out"]
        return (catmull_rom_tangents(self.key_times, self.pos_keys),
                catmull_rom_tangents(self.key_times, self.rot_keys))

    def spline_basis(self, t: float) -> tuple[int, int, torch.Tensor]:
        """``(lo, hi, b [hi - lo])`` with ``ξ(t) = Σ_k b_k keys[:, lo + k]`` for Catmull-Rom
        tangents (the other keys have weight 0 at ``t``).

        Catmull-Rom tangents are linear in the keys, so the whole spline is
        (:func:`~engine.geometry.hermite.hermite_basis_matrix`); evaluating it as one
        ``[K]``-weighted sum replaces ~50 small ``[N, K, C]`` ops per evaluation and their
        backward. Computed in float64 numpy (microseconds) and cached per time while the
        key times are unchanged (their ``_version`` moves on any in-place edit).
        """
        kt = self.key_times
        key = (float(t), id(kt), kt._version)
        cache = self.__dict__.setdefault("_basis_cache", {})
        hit = cache.get(key)
        if hit is None:
            b = catmull_rom_basis(kt.detach().cpu().double().numpy(), float(t))
            nz = np.nonzero(b)[0]
            lo, hi = (int(nz[0]), int(nz[-1]) + 1) if len(nz) else (0, 1)
            # at most 4 keys carry weight (the segment's ends and their tangent neighbours)
            hit = (lo, hi, torch.from_numpy(b[lo:hi]).to(device=kt.device, dtype=self.pos_keys.dtype))
            if len(cache) > 512:  # random ARAP times would otherwise grow it without bound
                cache.clear()
            cache[key] = hit
        return hit

    def node_state(self, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Node positions ``p_i(t)`` [N, 3] and unit quaternions ``q_i(t)`` [N, 4] at time ``t``."""
        if self.mlp is not None:
            dp, q = self.mlp(self.node_centers, t)
            return self.node_centers + dp, q
        if getattr(self, "explicit_tangents", None) is None:
            # Catmull-Rom: the spline is the basis-weighted sum of the keys (same values as
            # hermite_eval with catmull_rom_tangents, to float rounding)
            if self._fused_nodes():
                return self.node_state_dq(t)[:2]
            lo, hi, b = self.spline_basis(t)
            b = b[None, :, None]
            pos = (self.pos_keys[:, lo:hi] * b).sum(1)
            return pos, quat_normalize((self.rot_keys[:, lo:hi] * b).sum(1))
        tt = torch.tensor([float(t)], device=self.key_times.device, dtype=self.key_times.dtype)
        pos_tan, rot_tan = self.node_tangents()
        explicit = getattr(self, "explicit_tangents", None)
        pos_in = explicit["pos_in"] if explicit else None
        rot_in = explicit["rot_in"] if explicit else None
        pos = hermite_eval(self.key_times, self.pos_keys, pos_tan, tt, tangents_in=pos_in)[:, 0]
        rot = hermite_eval_quat(self.key_times, self.rot_keys, rot_tan, tt, tangents_in=rot_in)[:, 0]
        return pos, rot

    def _fused_nodes(self) -> bool:
        """Whether :meth:`node_state_dq` takes the fused CPU kernel (Catmull-Rom splines)."""
        return (FUSED_NODES and self.mlp is None and getattr(self, "explicit_tangents", None) is None
                and fused_available(self.pos_keys, self.rot_keys, self.node_centers))

    def node_state_dq(self, t: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`node_state` at ``t`` and the node transforms as dual quaternions ``[N, 8]``
        (:func:`~engine.geometry.dualquat.node_transforms_dq`): what a training step needs,
        in one fused pass on the CPU for Catmull-Rom splines (``engine/train/fused_nodes.py``;
        the torch ops are the reference)."""
        if self._fused_nodes():
            lo, _hi, b = self.spline_basis(t)
            return fused_node_state(self.pos_keys, self.rot_keys, lo, b, self.node_centers)
        pos, rot = self.node_state(t)
        return pos, rot, node_transforms_dq(self.node_centers, pos, rot)

    def times_basis(self, times) -> torch.Tensor:
        """Catmull-Rom weights ``[T, K]`` of the keys at each of ``times`` (T floats; the rows of
        :meth:`spline_basis`, zeros included), float64, cached while the key times are
        unchanged (a run asks for the same sets of times again and again: its training
        frames, the seed times of its moving Gaussians)."""
        times = tuple(float(t) for t in times)
        kt = self.key_times
        key = (times, id(kt), kt._version)
        cache = self.__dict__.setdefault("_times_basis_cache", {})
        hit = cache.get(key)
        if hit is None:
            kt_np = kt.detach().cpu().double().numpy()
            hit = torch.from_numpy(np.stack([catmull_rom_basis(kt_np, t) for t in times]))
            if len(cache) > 256:
                cache.clear()
            cache[key] = hit
        return hit

    def node_states(self, times, nodes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions ``[S, T, 3]`` and unit quaternions ``[S, T, 4]`` of the nodes ``nodes [S]``
        (default all) at each of ``times`` (T floats): :meth:`node_state` at every time, in
        one basis-matrix product for Catmull-Rom splines (the same weights as
        :meth:`spline_basis`), else time by time."""
        times = [float(t) for t in times]
        sel = (lambda x: x) if nodes is None else (lambda x: x[nodes])  # noqa: E731
        if self.mlp is None and getattr(self, "explicit_tangents", None) is None and times:
            basis = self.times_basis(times).to(self.pos_keys)
            pos = torch.einsum("tk,nkc->ntc", basis, sel(self.pos_keys))
            return pos, quat_normalize(torch.einsum("tk,nkc->ntc", basis, sel(self.rot_keys)))
        states = [self.node_state(t) for t in times]
        if not states:
            n = self.num_nodes if nodes is None else len(nodes)
            return self.node_centers.new_zeros(n, 0, 3), self.node_centers.new_zeros(n, 0, 4)
        pos = torch.stack([sel(p) for p, _ in states], 1)
        return pos, torch.stack([quat_normalize(sel(q)) for _, q in states], 1)

    def gaussian_transforms(self, t: float, bind_idx=None, bind_w=None) -> torch.Tensor:
        """Blended unit dual quaternions [G, 8] moving canonical Gaussians to time ``t``."""
        pos, rot = self.node_state(t)
        dq_nodes = node_transforms_dq(self.node_centers, pos, rot)
        return dq_blend(dq_nodes, self.bind_idx if bind_idx is None else bind_idx,
                        self.bind_w if bind_w is None else bind_w)

    def node_dq(self, t: float) -> torch.Tensor:
        """Node transforms at time ``t`` as unit dual quaternions [N, 8]."""
        return self.node_state_dq(t)[2]

    def deform(self, t: float, dq_nodes: torch.Tensor | None = None,
               index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussian centres [G, 3] and rotations [G, 4] at time ``t``.

        ``dq_nodes [N, 8]``: the node transforms at ``t`` when the caller already has them
        (:meth:`node_dq`; the training step shares one evaluation between its terms).
        ``index [L]``: deform only these rows (then ``[L, 3]`` / ``[L, 4]``; the training step
        leaves out the Gaussians outside their lifespan window,
        :func:`~engine.train.lifespan.shown_gaussians`).
        """
        means, quats, bind_idx, bind_w = self.means, self.quats, self.bind_idx, self.bind_w
        if index is not None:
            means, quats, bind_idx, bind_w = means[index], quats[index], bind_idx[index], bind_w[index]
        if FUSED_DEFORM and fused_available(means, quats, bind_w):
            # one Numba pass (forward + hand-written backward) instead of ~100 [G, K, 8]
            # torch ops; same values as the torch reference below (engine/train/fused.py),
            # the static Gaussians passed through unblended
            dq_nodes = self.node_dq(t) if dq_nodes is None else dq_nodes
            return fused_deform(dq_nodes, bind_idx, bind_w, means, quats, normalize=True,
                                node_rest=resting_nodes(self, dq_nodes))
        dq_nodes = self.node_dq(t) if dq_nodes is None else dq_nodes
        dq = dq_blend(dq_nodes, bind_idx, bind_w)
        return dq_apply_points(dq, means), dq_apply_rotations(dq, quat_normalize(quats))

    def deform_points(self, points: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, t: float,
                      dq_nodes: torch.Tensor | None = None) -> torch.Tensor:
        """Move arbitrary canonical points [P, 3] bound by (idx, w) [P, K_b] to time ``t``
        (``dq_nodes [N, 8]`` as in :meth:`deform`)."""
        dq_nodes = self.node_dq(t) if dq_nodes is None else dq_nodes
        if FUSED_DEFORM and fused_available(points, w):
            ident = points.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(points.shape[0], 4)
            return fused_deform(dq_nodes, idx, w, points, ident)[0]
        return dq_apply_points(dq_blend(dq_nodes, idx, w), points)

    # ------------------------------------------------------------------ export
    @torch.no_grad()
    def export_splines(self, sample_times: torch.Tensor | None = None):
        """Node splines as arrays for the bundle.

        For the MLP model (no keys) the motion is sampled at ``sample_times`` and
        returned as a Catmull-Rom spline through the samples, so Blender still gets
        F-curves (documented as an approximation of the MLP).
        """
        if self.mlp is None:
            pos_tan, rot_tan = self.node_tangents()
            pos_tan, rot_tan = pos_tan.detach(), rot_tan.detach()
            return self.key_times, self.pos_keys.detach(), pos_tan, quat_normalize(self.rot_keys.detach()), rot_tan
        if sample_times is None:
            sample_times = torch.linspace(0, 1, 16, device=self.node_centers.device)
        pos, rot = zip(*(self.node_state(float(t)) for t in sample_times))
        pos = torch.stack(pos, 1)
        rot = torch.stack(rot, 1)
        # keep quaternion signs continuous along time (q and -q are the same rotation)
        dots = (rot[:, 1:] * rot[:, :-1]).sum(-1)
        sign = torch.where(dots < 0, -torch.ones_like(dots), torch.ones_like(dots)).cumprod(1)
        rot = torch.cat([rot[:, :1], rot[:, 1:] * sign.unsqueeze(-1)], 1)
        return (sample_times, pos, catmull_rom_tangents(sample_times, pos), rot,
                catmull_rom_tangents(sample_times, rot))
