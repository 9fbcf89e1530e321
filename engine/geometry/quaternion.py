"""Unit quaternions, scalar first ``(w, x, y, z)`` as in Blender.

All functions broadcast over leading dimensions and work for any float dtype/device.
"""

from __future__ import annotations

import torch


def quat_normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``q / |q|`` for ``[..., 4]``; a zero quaternion becomes the identity."""
    n = q.norm(dim=-1, keepdim=True)
    # a broadcast [C] constant instead of a zeros_like + fill of q's whole shape
    ident = q.new_zeros(q.shape[-1])
    ident[0] = 1
    return torch.where(n > eps, q / n.clamp_min(eps), ident)


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate ``(w, -x, -y, -z)``; the inverse of a unit quaternion."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b`` of ``[..., 4]`` tensors (rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def quat_apply(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v [..., 3]`` by unit quaternions ``q [..., 4]``.

    Uses ``v + 2w (u × v) + 2 u × (u × v)`` (no matrix), valid for unit ``q``.
    """
    u, v = torch.broadcast_tensors(q[..., 1:], v)  # either side may carry the batch dims
    w = q[..., :1]
    uv = torch.cross(u, v, dim=-1)
    return v + 2.0 * (w * uv + torch.cross(u, uv, dim=-1))


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` of unit quaternions ``[..., 4]``."""
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return torch.stack([
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def quat_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``[..., 4]`` (with ``w >= 0``) of rotation matrices ``[..., 3, 3]``.

    Branch-free Shepperd method: computes the four candidate solutions and keeps, per
    matrix, the one with the largest (best conditioned) denominator.
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    diag = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    cands = torch.stack([
        torch.stack([diag[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, diag[..., 1], m10 + m01, m02 + m20], -1),
        torch.stack([m02 - m20, m10 + m01, diag[..., 2], m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, diag[..., 3]], -1),
    ], dim=-2)  # [..., 4 candidates, 4]
    best = diag.argmax(dim=-1)
    denom = 2.0 * torch.sqrt(diag.gather(-1, best.unsqueeze(-1)).clamp_min(1e-12))
    q = cands.gather(-2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2) / denom
    q = quat_normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_identity(*shape: int, dtype=None, device=None) -> torch.Tensor:
    """Identity quaternions ``[*shape, 4]`` (``(1, 0, 0, 0)``)."""
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1
    return q


def quat_from_axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Quaternions ``[..., 4]`` rotating by ``angle [...]`` (radians) about ``axis [..., 3]``."""
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    half = 0.5 * angle
    return torch.cat([torch.cos(half).unsqueeze(-1), torch.sin(half).unsqueeze(-1) * axis], dim=-1)


def quat_to_rotation_vector(q: torch.Tensor) -> torch.Tensor:
    """Axis times angle ``[..., 3]`` (radians, the angle in ``[0, pi]``) of unit quaternions
    ``[..., 4]``; the inverse of :func:`quat_from_axis_angle` with ``angle = |v|``."""
    q = torch.where(q[..., :1] < 0, -q, q)  # q and -q are one rotation: take the short way round
    s = q[..., 1:].norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    # angle / s -> 2 as the rotation vanishes (sin(a/2) ~ a/2)
    return q[..., 1:] * torch.where(s > 1e-12, angle / s.clamp_min(1e-12), torch.full_like(s, 2.0))
