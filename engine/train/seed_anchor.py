"""Moving Gaussians held at their own frame while the node keys train (``TrainConfig.lifespan_anchor``).

A moving Gaussian with a lifespan (``engine/train/lifespan.py``) is seeded from one training
frame, back-projected along that frame's pixel rays, and shows mostly around it. Its
canonical centre is the seeded point moved back through the nodes' motion at its seed time
``t_s``. Every step moves the spline keys (one frame's photometric gradient, the track and
graph terms, Adam's momentum on every key), so at ``t_s`` a canonical Gaussian drifts off
the pixel it was seeded on, and the training views lose the per-frame detail the seeds
carried: with the node keys frozen the large-motion scenes' moving regions score ~25 dB on
their training views, trained ~21 (docs/benchmarks.md, *A moving Gaussian held at its seed
frame*).

So while the keys train, those Gaussians are held in their **seed frame**: their rows of
``means`` / ``quats`` hold the world centre and rotation at ``t_s`` (:func:`to_seed_frame_`),
and a render at time ``t`` moves them by ``B(t) B(t_s)^-1`` (:func:`deform_seed_frame`): the
keys learn only a Gaussian's motion relative to its seed frame, nothing at the frame itself,
and no key step can move it off its seed pixel. (With the plain gradient of a canonical
Gaussian the keys ran off by a median 0.84 units over a run on the large scenes, and the
moving regions gained under a dB.) Whatever needs canonical poses (a rebind, node
densification, a render outside the step, the bundle) sees them through
:func:`canonical_view` or after :func:`to_canonical_`.

Why a second parametrisation rather than canonical centres re-anchored after each step (the
first version, b935ecd): that re-expressed every held row after every step (two blends over
all of them, ~40 ms a step on the large scenes' 120k seeds), where the seed frame costs only
the rows a step draws.

The bundle, the Blender rig and every reader see an ordinary canonical model.
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


def _seed_index(model, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct seed times ``[S]`` of ``rows`` and each row's binding ``[A, K]`` into an
    ``[S*N, 8]`` table of the node transforms at those times (so one blend serves Gaussians
    of many times)."""
    times, which = torch.unique(model.gauss_t_center[rows], return_inverse=True)  # [S], [A]
    return times, model.bind_idx[rows] + (which * model.num_nodes)[:, None]


def _table(model, times: torch.Tensor, keys_learn: bool = False) -> torch.Tensor:
    """The node transforms at ``times [S]`` as one ``[S*N, 8]`` table
    (:meth:`~engine.train.model.DynamicScene.node_states`), differentiable in the keys only if
    ``keys_learn``."""
    with torch.set_grad_enabled(keys_learn and torch.is_grad_enabled()):
        pos, rot = model.node_states(times.tolist())  # [N, S, 3], [N, S, 4]
        dq = node_transforms_dq(model.node_centers[:, None].expand_as(pos), pos, rot)
    return dq.transpose(0, 1).reshape(-1, 8)


def _apply(table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, means: torch.Tensor, quats: torch.Tensor):
    """Blend ``table`` by ``(idx, w)`` and move ``means [A, 3]`` / ``quats [A, 4]`` (any norm)
    with it: the fused kernel where it runs, the torch reference otherwise."""
    if fused_available(table, means, quats, w):
        return fused_deform(table, idx, w, means, quats, normalize=True)
    dq = dq_blend(table, idx, w)
    return dq_apply_points(dq, means), dq_apply_rotations(dq, quat_normalize(quats))


@torch.no_grad()
def seed_poses(model, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World centres ``[A, 3]`` and unit rotations ``[A, 4]`` of canonical ``rows`` at their
    seed times."""
    times, idx = _seed_index(model, rows)
    return _apply(_table(model, times), idx, model.bind_w[rows], model.means[rows], model.quats[rows])


@torch.no_grad()
def canonical_poses(model, rows: torch.Tensor, x_s: torch.Tensor,
                    q_s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The canonical centres ``[A, 3]`` and unit rotations ``[A, 4]`` that the model's current
    keys and binding put at ``x_s [A, 3]`` / ``q_s [A, 4]`` at the seed times of ``rows``."""
    times, idx = _seed_index(model, rows)
    # the blend of the inverted node transforms is the inverse of the blend (DQB is linear
    # in the transforms, and the conjugate keeps norms and hemispheres)
    return _apply(dq_inverse(_table(model, times)), idx, model.bind_w[rows], x_s, q_s)


@torch.no_grad()
def _write_(model, rows: torch.Tensor, means: torch.Tensor, quats: torch.Tensor) -> None:
    """Set ``rows`` of the centres and rotations; the rotations keep their norm (Adam's state
    is in it)."""
    norm = model.quats[rows].norm(dim=-1, keepdim=True)
    model.means[rows] = means
    model.quats[rows] = quat_normalize(quats) * norm


def to_seed_frame_(model) -> None:
    """Canonical -> seed frame, in place, for the :func:`anchored_rows` (each row's centre and
    rotation become its world pose at its seed time)."""
    rows = anchored_rows(model)
    if len(rows):
        _write_(model, rows, *seed_poses(model, rows))


def to_canonical_(model) -> None:
    """Seed frame -> canonical, in place, for the :func:`anchored_rows`, with the model's current
    keys and binding (the inverse of :func:`to_seed_frame_`)."""
    rows = anchored_rows(model)
    if len(rows):
        _write_(model, rows, *canonical_poses(model, rows, model.means[rows], model.quats[rows]))


def hold_seed_frame_(model, held: bool, hold: bool) -> bool:
    """Convert ``model`` (in the seed frame if ``held``) so that it is in the seed frame if
    ``hold``, canonical otherwise; returns ``hold``."""
    if hold and not held:
        to_seed_frame_(model)
    elif held and not hold:
        to_canonical_(model)
    return hold


@contextmanager
def canonical_view(model, active: bool = True):
    """Inside the block a model held in its seed frame (``active``) shows canonical poses (for a
    rebind, node densification, a render, an export); after it every held row is back at
    exactly the seed-frame pose it had, whatever the block did to the binding or the node
    numbering (rows themselves must not change inside it)."""
    if not active:
        yield
        return
    rows = anchored_rows(model)
    kept = (model.means[rows].detach().clone(), model.quats[rows].detach().clone())
    to_canonical_(model)
    try:
        yield
    finally:
        with torch.no_grad():
            model.means[rows] = kept[0]
            model.quats[rows] = kept[1]


def deform_seed_frame(model, t: float, dq_nodes: torch.Tensor, index: torch.Tensor, relative: bool = True):
    """Centres ``[L, 3]`` and rotations ``[L, 4]`` at time ``t`` of rows ``index [L]`` of a model
    held in its seed frame (:func:`to_seed_frame_`).

    The rows with a lifespan move by ``B(t) B(t_s)^-1`` from their seed-frame pose (at ``t =
    t_s`` the pose is the row's own, to float rounding); the others deform as in
    :meth:`~engine.train.model.DynamicScene.deform`. ``dq_nodes [N, 8]``: node transforms at
    ``t`` (:meth:`~engine.train.model.DynamicScene.node_dq`). ``relative``: the keys learn through
    both transforms, i.e. only the motion relative to the seed frame (what the render needs: the
    seed frame's own pixels cannot pull its keys); False: through ``B(t)`` alone, as for a
    canonical Gaussian (the pull of the Gaussians onto the moving pixels of other frames,
    ``Objective.on_mask``, which moves the keys at ``t`` to bring them there).
    """
    life = model.gauss_lifespan[index] > 0
    if not _holds(model) or not bool(life.any()):
        return model.deform(t, dq_nodes=dq_nodes, index=index)
    rows_l, rows_o = index[life], index[~life]
    times, idx_s = _seed_index(model, rows_l)
    table = _table(model, times, keys_learn=relative)
    w_l = model.bind_w[rows_l]
    c, q_c = _apply(dq_inverse(table), idx_s, w_l, model.means[rows_l], model.quats[rows_l])
    x_l, q_l = _apply(dq_nodes, model.bind_idx[rows_l], w_l, c, q_c)
    if len(rows_o) == 0:
        return x_l, q_l
    x_o, q_o = model.deform(t, dq_nodes=dq_nodes, index=rows_o)
    at_l, at_o = torch.nonzero(life).squeeze(1), torch.nonzero(~life).squeeze(1)
    means_t = x_l.new_empty(len(index), 3).index_put((at_l,), x_l).index_put((at_o,), x_o)
    quats_t = q_l.new_empty(len(index), 4).index_put((at_l,), q_l).index_put((at_o,), q_o)
    return means_t, quats_t
