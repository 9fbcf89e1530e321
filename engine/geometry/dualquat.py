"""Unit dual quaternions and dual-quaternion blending (DQB, Kavan et al. 2007).

A dual quaternion is a ``[..., 8]`` tensor: real part ``q_r`` (wxyz) then dual part
``q_d = ½ t ⊗ q_r`` for the rigid transform ``x ↦ R(q_r) x + t``.
"""

from __future__ import annotations

import torch

from .quaternion import quat_apply, quat_conj, quat_from_matrix, quat_mul, quat_normalize, quat_to_matrix


def _pure(v: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.zeros_like(v[..., :1]), v], dim=-1)


def dq_from_rt(q: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Rotation ``q [..., 4]`` (unit) and translation ``t [..., 3]`` -> ``[..., 8]``."""
    q = q.expand(torch.broadcast_shapes(q.shape[:-1], t.shape[:-1]) + (4,))
    return torch.cat([q, 0.5 * quat_mul(_pure(t).expand(q.shape), q)], dim=-1)


def dq_to_rt(dq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``[..., 8]`` -> unit rotation ``[..., 4]`` and translation ``[..., 3]``.

    Normalises the real part first; a dual part with a component along ``q_r`` (which
    blending can introduce) only affects the scalar of ``q_d q_r*`` and is ignored.
    """
    n = dq[..., :4].norm(dim=-1, keepdim=True).clamp_min(1e-12)
    qr = dq[..., :4] / n
    qd = dq[..., 4:] / n
    t = 2.0 * quat_mul(qd, quat_conj(qr))[..., 1:]
    return qr, t


def dq_from_se3(T: torch.Tensor) -> torch.Tensor:
    """Rigid transforms ``[..., 4, 4]`` -> dual quaternions ``[..., 8]``."""
    return dq_from_rt(quat_from_matrix(T[..., :3, :3]), T[..., :3, 3])


def dq_to_se3(dq: torch.Tensor) -> torch.Tensor:
    """Dual quaternions ``[..., 8]`` -> rigid transforms ``[..., 4, 4]``."""
    q, t = dq_to_rt(dq)
    T = torch.zeros(dq.shape[:-1] + (4, 4), dtype=dq.dtype, device=dq.device)
    T[..., :3, :3] = quat_to_matrix(q)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def dq_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Product ``a ⊗ b`` (apply ``b`` first)."""
    ar, ad = a[..., :4], a[..., 4:]
    br, bd = b[..., :4], b[..., 4:]
    return torch.cat([quat_mul(ar, br), quat_mul(ar, bd) + quat_mul(ad, br)], dim=-1)


def dq_normalize(dq: torch.Tensor) -> torch.Tensor:
    """Divide by the norm of the real part (the DQB normalisation)."""
    return dq / dq[..., :4].norm(dim=-1, keepdim=True).clamp_min(1e-12)


def dq_inverse(dq: torch.Tensor) -> torch.Tensor:
    """Inverse of unit dual quaternions: conjugate both quaternion parts."""
    return torch.cat([quat_conj(dq[..., :4]), quat_conj(dq[..., 4:])], dim=-1)


def dq_blend(dq: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Dual-quaternion blending of ``K`` node transforms per output.

    Parameters
    ----------
    dq : (..., N, 8) unit dual quaternions of the nodes (leading dims, e.g. times,
        are batched over).
    idx : (G, K) long, node indices per output (e.g. per Gaussian).
    w : (G, K) or (..., G, K) blend weights (normally summing to 1).

    Returns
    -------
    (..., G, 8) unit dual quaternions. Each neighbour's sign is aligned with the
    neighbour of largest weight (``q`` and ``−q`` are the same rotation; blending must
    not mix the two hemispheres, or antipodal inputs cancel), then ``Σ w_k Q_k`` is
    normalised by its real part's norm.
    """
    nb = dq[..., idx, :]  # [..., G, K, 8]
    w = w.to(dq.dtype).expand(nb.shape[:-1])
    pivot = w.argmax(dim=-1, keepdim=True)  # [..., G, 1]
    ref = nb[..., :4].gather(-2, pivot.unsqueeze(-1).expand(pivot.shape + (4,)))  # [..., G, 1, 4]
    dot = (nb[..., :4] * ref).sum(-1, keepdim=True)
    sign = torch.where(dot < 0, -torch.ones_like(dot), torch.ones_like(dot))
    blended = (w.unsqueeze(-1) * sign * nb).sum(-2)
    return dq_normalize(blended)


def dq_apply_points(dq: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Apply ``[..., 8]`` transforms to points ``[..., 3]``."""
    q, t = dq_to_rt(dq)
    return quat_apply(q, x) + t


def dq_apply_rotations(dq: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Left-multiply rotations ``q [..., 4]`` (e.g. Gaussian orientations) by the
    rotation part of ``dq [..., 8]``; returns unit quaternions."""
    return quat_normalize(quat_mul(quat_normalize(dq[..., :4]), q))


def node_transforms_dq(centers: torch.Tensor, positions: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """Dual quaternions of the node transforms ``x ↦ R(q_i)(x − c_i) + p_i``.

    Parameters
    ----------
    centers : (N, 3) canonical centres ``c_i``.
    positions : (N, 3) positions ``p_i(t)``.
    quats : (N, 4) rotations ``q_i(t)`` (normalised here).

    Returns
    -------
    (N, 8): rotation ``q_i`` with translation ``p_i − R(q_i) c_i``.
    """
    q = quat_normalize(quats)
    return dq_from_rt(q, positions - quat_apply(q, centers))


def deform_points(centers, positions, quats, idx, w, x) -> torch.Tensor:
    """Move canonical points ``x [G, 3]`` by DQB of node transforms (see above)."""
    return dq_apply_points(dq_blend(node_transforms_dq(centers, positions, quats), idx, w), x)
