"""Moving Gaussians held at their own frame while the node keys train (``TrainConfig.lifespan_anchor``).

A moving Gaussian with a lifespan (``engine/train/lifespan.py``) is seeded from one training
frame, back-projected along that frame's pixel rays, and shows mostly around it. Its
canonical centre is the seeded point moved back through the nodes' motion at its seed time
``t_s``. Every step moves the spline keys (one frame's photometric gradient, the track and
graph terms, Adam's momentum on every key), so at ``t_s`` the Gaussian drifts off the pixel
it was seeded on, and the training views lose the per-frame detail the seeds carried: with
the node keys frozen the large-motion scenes' moving regions score ~25 dB on their training
views, trained ~21 (docs/benchmarks.md, *A moving Gaussian held at its seed frame*).

Two parts, both needed:

* :func:`anchor_to_seed_time_` after each optimiser step (and :func:`seed_poses` /
  :func:`restore_seed_poses_` around a rebind or densification): each such Gaussian's
  canonical centre and rotation are re-expressed so that the nodes' new state at ``t_s``
  puts it where the old state did.
* :func:`deform_seed_relative` in the step's forward pass: the same centres, with the
  gradient of ``B(t) B(t_s)^-1 sg[B(t_s)] c``, so the keys learn only a Gaussian's motion
  relative to its seed frame. With the plain gradient the anchoring undoes every step's
  effect on a Gaussian's own frame and its gradient pushes the keys on without end (the keys
  ran off by a median 0.84 units over a run on the large scenes, and their moving regions
  gained under a dB over no anchoring).

The model's representation is unchanged (canonical centres, one binding): the bundle,
the Blender rig and every reader see an ordinary model.
"""
from __future__ import annotations

from contextlib import contextmanager

import torch

from ..geometry.dualquat import dq_apply_points, dq_apply_rotations, dq_blend, dq_inverse, node_transforms_dq
from ..geometry.quaternion import quat_normalize
from .fused import fused_available, fused_deform


def _holds(model) -> bool:
    """Whether ``model``'s motion can hold Gaussians at their seed times: Catmull-Rom spline
    keys (the MLP has none; explicit tangents, from a bundle, are not what training moves)."""
    return model.mlp is None and model.pos_keys is not None and getattr(model, "explicit_tangents", None) is None


def anchored_rows(model) -> torch.Tensor:
    """Rows ``[A]`` of the Gaussians held at their seed time: those with a lifespan, on a
    model whose motion :func:`_holds` them."""
    if not _holds(model):
        return torch.zeros(0, dtype=torch.long, device=model.means.device)
    return torch.nonzero(model.gauss_lifespan > 0).squeeze(1)


def node_dq_at_times(model, pos_keys: torch.Tensor, rot_keys: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """Node transforms ``[S, N, 8]`` at ``times [S]`` for the keys ``pos_keys [N, K, 3]``,
    ``rot_keys [N, K, 4]`` on ``model``'s key times (Catmull-Rom, as
    :meth:`~engine.train.model.DynamicScene.node_states`); differentiable in the keys."""
    basis = model.times_basis(times.tolist()).to(pos_keys)
    pos = torch.einsum("sk,nkc->snc", basis, pos_keys)
    rot = quat_normalize(torch.einsum("sk,nkc->snc", basis, rot_keys))
    return node_transforms_dq(model.node_centers.expand_as(pos), pos, rot)


def _seed_index(model, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct seed times ``[S]`` of ``rows`` and each row's binding ``[A, K]`` into an
    ``[S*N, 8]`` table of the node transforms at those times (so one blend serves Gaussians
    of many times)."""
    times, which = torch.unique(model.gauss_t_center[rows], return_inverse=True)  # [S], [A]
    return times, model.bind_idx[rows] + (which * model.num_nodes)[:, None]


def _table(model, times: torch.Tensor, pos_keys: torch.Tensor | None = None,
           rot_keys: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`node_dq_at_times` as one ``[S*N, 8]`` table, with the model's current keys
    (detached) unless others are given."""
    pos_keys = model.pos_keys.detach() if pos_keys is None else pos_keys
    rot_keys = model.rot_keys.detach() if rot_keys is None else rot_keys
    return node_dq_at_times(model, pos_keys, rot_keys, times).reshape(-1, 8)


def _apply(table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, means: torch.Tensor, quats: torch.Tensor):
    """Blend ``table`` by ``(idx, w)`` and move ``means [A, 3]`` / ``quats [A, 4]`` (any norm)
    with it: the fused kernel where it runs, the torch reference otherwise."""
    if fused_available(table, means, quats, w):
        return fused_deform(table, idx, w, means, quats, normalize=True)
    dq = dq_blend(table, idx, w)
    return dq_apply_points(dq, means), dq_apply_rotations(dq, quat_normalize(quats))


@torch.no_grad()
def seed_poses(model, rows: torch.Tensor, pos_keys: torch.Tensor | None = None,
               rot_keys: torch.Tensor | None = None, index=None) -> tuple[torch.Tensor, torch.Tensor]:
    """World centres ``[A, 3]`` and unit rotations ``[A, 4]`` of ``rows`` at their seed times
    (with the keys given, default the model's own; ``index``: :func:`_seed_index` of ``rows``
    when the caller has it)."""
    times, idx = _seed_index(model, rows) if index is None else index
    return _apply(_table(model, times, pos_keys, rot_keys), idx, model.bind_w[rows], model.means[rows],
                  model.quats[rows])


@torch.no_grad()
def restore_seed_poses_(model, rows: torch.Tensor, x_s: torch.Tensor, q_s: torch.Tensor, index=None) -> None:
    """Set the canonical centres / rotations of ``rows`` so that the model's current keys and
    binding put them at ``x_s [A, 3]`` / ``q_s [A, 4]`` at their seed times (in place; the
    rotations keep their norm, which Adam's state is in; ``index`` as in :func:`seed_poses`)."""
    if len(rows) == 0:
        return
    times, idx = _seed_index(model, rows) if index is None else index
    # the blend of the inverted node transforms is the inverse of the blend (DQB is linear
    # in the transforms, and the conjugate keeps norms and hemispheres)
    c, q_c = _apply(dq_inverse(_table(model, times)), idx, model.bind_w[rows], x_s, q_s)
    norm = model.quats[rows].norm(dim=-1, keepdim=True)
    model.means[rows] = c
    model.quats[rows] = quat_normalize(q_c) * norm


@torch.no_grad()
def anchor_to_seed_time_(model, pos_keys_before: torch.Tensor, rot_keys_before: torch.Tensor) -> None:
    """After an optimiser step: re-express the :func:`anchored_rows` so that at their seed
    times the nodes' current keys put them where ``pos_keys_before [N, K, 3]`` /
    ``rot_keys_before [N, K, 4]`` did (their own trained centres included)."""
    rows = anchored_rows(model)
    if len(rows):
        index = _seed_index(model, rows)  # the same rows and binding before and after the step
        restore_seed_poses_(model, rows, *seed_poses(model, rows, pos_keys_before, rot_keys_before, index), index)


@contextmanager
def seed_poses_kept(model, active: bool = True):
    """Keep the :func:`anchored_rows` at their seed-time poses across a block that rebinds
    the Gaussians or renumbers the nodes (rows themselves must not change inside it)."""
    if not active:
        yield
        return
    rows = anchored_rows(model)
    pose = seed_poses(model, rows) if len(rows) else None
    yield
    if pose is not None:
        restore_seed_poses_(model, anchored_rows(model), *pose)


def deform_seed_relative(model, t: float, dq_nodes: torch.Tensor, index: torch.Tensor):
    """Centres ``[L, 3]`` and rotations ``[L, 4]`` of rows ``index [L]`` at time ``t``.

    The values of :meth:`~engine.train.model.DynamicScene.deform`; for the rows with a
    lifespan the gradient is that of ``B(t) B(t_s)^-1 sg[B(t_s)] c``: the node keys learn
    only a Gaussian's motion relative to its seed frame (none at the seed frame itself);
    centres and rotations get their usual gradient. ``dq_nodes [N, 8]``: node transforms at
    ``t`` (:meth:`~engine.train.model.DynamicScene.node_dq`).
    """
    life = model.gauss_lifespan[index] > 0
    if not _holds(model) or not bool(life.any()):
        return model.deform(t, dq_nodes=dq_nodes, index=index)
    rows_l, rows_o = index[life], index[~life]
    times, idx_s = _seed_index(model, rows_l)
    table = _table(model, times, model.pos_keys, model.rot_keys)  # differentiable in the keys
    w_l = model.bind_w[rows_l]
    x_s, q_s = _apply(table.detach(), idx_s, w_l, model.means[rows_l], model.quats[rows_l])
    c, q_c = _apply(dq_inverse(table), idx_s, w_l, x_s, q_s)
    x_l, q_l = _apply(dq_nodes, model.bind_idx[rows_l], w_l, c, q_c)
    if len(rows_o) == 0:
        return x_l, q_l
    x_o, q_o = model.deform(t, dq_nodes=dq_nodes, index=rows_o)
    at_l, at_o = torch.nonzero(life).squeeze(1), torch.nonzero(~life).squeeze(1)
    means_t = x_l.new_empty(len(index), 3).index_put((at_l,), x_l).index_put((at_o,), x_o)
    quats_t = q_l.new_empty(len(index), 4).index_put((at_l,), q_l).index_put((at_o,), q_o)
    return means_t, quats_t
