"""Fused CPU node state: the Catmull-Rom spline of every node at one time and its node
transform as a dual quaternion, in one Numba pass with a hand-written backward.

Per training step the trainer evaluates the node splines at the step's time (positions,
rotations and the dual quaternions the deformation blends) and at a second time for ARAP.
In torch that is ~40 small ``[N, ...]`` ops and as many in the backward (key slices,
products, sums, two quaternion normalisations, a rotation, a quaternion product): about
2.5 ms a step at 1k nodes on two cores, nearly all per-op overhead. Here it is one serial
pass in float64 (a few tens of microseconds). The torch path stays the reference (and the
GPU path): :meth:`engine.train.model.DynamicScene.node_state` with
:func:`engine.geometry.dualquat.node_transforms_dq`; ``tests/engine/test_fused_nodes.py``
checks values and gradients against it.

forward (per node ``i``; ``b [S]`` the basis weights of keys ``lo .. lo + S - 1`` at ``t``)
    ``p = Σ_k b_k P_ik``, ``r = Σ_k b_k Q_ik``, ``u = r / |r|`` (the rotation output; the
    identity for ``|r| <= 1e-12``), ``q = u / |u|`` (as ``node_transforms_dq`` normalises
    again), ``τ = p − R(q) c_i`` with ``R(q) c = c + 2w (v × c) + 2 v × (v × c)``, and the
    dual quaternion ``(q, ½ (0, τ) ⊗ q)``.
backward
    the same chain in reverse: the dual part to ``τ`` and ``q``, ``τ`` to ``p`` and ``q``,
    both normalisations, then ``b_k`` times each key's share.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from .fused import _f32  # float32 C-contiguous NumPy view (no copy for float32 tensors)

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
# quat_normalize's threshold, the same as fused_reg.EPS (a test ties the copies together).
# Not imported from there: a cached kernel freezes the globals it reads, and Numba's cache
# checks only the kernel's own source file, so an edit to fused_reg.py would leave this
# module's cached kernels with the old value.
EPS = 1e-12


@njit(inline="always", **_JIT)
def _qmul(aw, ax, ay, az, bw, bx, by, bz):
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


@njit(**_JIT)
def _forward(pk, rk, lo, b, c, pos, rot, dq, st):
    """``pk [N, K, 3]``, ``rk [N, K, 4]`` keys, ``b [S]`` weights of keys ``lo..``, ``c [N, 3]``
    centres; writes ``pos [N, 3]``, ``rot [N, 4]``, ``dq [N, 8]`` (float32) and the float64
    state the backward needs, ``st [N, 13]``: u (4), |r|, q (4), |u|, τ (3)."""
    N = pk.shape[0]
    S = b.shape[0]
    for i in range(N):
        px = py = pz = 0.0
        rw = rx = ry = rz = 0.0
        for k in range(S):
            bk = b[k]
            j = lo + k
            px += bk * pk[i, j, 0]
            py += bk * pk[i, j, 1]
            pz += bk * pk[i, j, 2]
            rw += bk * rk[i, j, 0]
            rx += bk * rk[i, j, 1]
            ry += bk * rk[i, j, 2]
            rz += bk * rk[i, j, 3]
        n1 = np.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
        if n1 > EPS:
            uw, ux, uy, uz = rw / n1, rx / n1, ry / n1, rz / n1
        else:
            uw, ux, uy, uz = 1.0, 0.0, 0.0, 0.0
        n2 = np.sqrt(uw * uw + ux * ux + uy * uy + uz * uz)
        if n2 > EPS:
            qw, qx, qy, qz = uw / n2, ux / n2, uy / n2, uz / n2
        else:
            qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        cx, cy, cz = np.float64(c[i, 0]), np.float64(c[i, 1]), np.float64(c[i, 2])
        # R(q) c = c + 2 w (v x c) + 2 v x (v x c)
        ax_ = qy * cz - qz * cy
        ay_ = qz * cx - qx * cz
        az_ = qx * cy - qy * cx
        bx_ = qy * az_ - qz * ay_
        by_ = qz * ax_ - qx * az_
        bz_ = qx * ay_ - qy * ax_
        tx = px - (cx + 2.0 * (qw * ax_ + bx_))
        ty = py - (cy + 2.0 * (qw * ay_ + by_))
        tz = pz - (cz + 2.0 * (qw * az_ + bz_))
        dw, dx, dy, dz = _qmul(0.0, tx, ty, tz, qw, qx, qy, qz)
        pos[i, 0], pos[i, 1], pos[i, 2] = px, py, pz
        rot[i, 0], rot[i, 1], rot[i, 2], rot[i, 3] = uw, ux, uy, uz
        dq[i, 0], dq[i, 1], dq[i, 2], dq[i, 3] = qw, qx, qy, qz
        dq[i, 4], dq[i, 5], dq[i, 6], dq[i, 7] = 0.5 * dw, 0.5 * dx, 0.5 * dy, 0.5 * dz
        st[i, 0], st[i, 1], st[i, 2], st[i, 3], st[i, 4] = uw, ux, uy, uz, n1
        st[i, 5], st[i, 6], st[i, 7], st[i, 8], st[i, 9] = qw, qx, qy, qz, n2
        st[i, 10], st[i, 11], st[i, 12] = tx, ty, tz


@njit(**_JIT)
def _backward(lo, b, c, st, g_pos, g_rot, g_dq, g_pk, g_rk):
    """Gradients of the keys ``g_pk [N, K, 3]``, ``g_rk [N, K, 4]`` (zero-filled by the
    caller; only keys ``lo .. lo + S - 1`` get any) from ``g_pos``, ``g_rot``, ``g_dq``."""
    N = st.shape[0]
    S = b.shape[0]
    for i in range(N):
        uw, ux, uy, uz, n1 = st[i, 0], st[i, 1], st[i, 2], st[i, 3], st[i, 4]
        qw, qx, qy, qz, n2 = st[i, 5], st[i, 6], st[i, 7], st[i, 8], st[i, 9]
        tx, ty, tz = st[i, 10], st[i, 11], st[i, 12]
        cx, cy, cz = np.float64(c[i, 0]), np.float64(c[i, 1]), np.float64(c[i, 2])
        # dual = ½ (0, τ) ⊗ q: g_(0,τ) = ½ g_d ⊗ q*, g_q = ½ (0, τ)* ⊗ g_d
        hw, hx, hy, hz = (0.5 * np.float64(g_dq[i, 4]), 0.5 * np.float64(g_dq[i, 5]),
                          0.5 * np.float64(g_dq[i, 6]), 0.5 * np.float64(g_dq[i, 7]))
        _, gtx, gty, gtz = _qmul(hw, hx, hy, hz, qw, -qx, -qy, -qz)
        gqw, gqx, gqy, gqz = _qmul(0.0, -tx, -ty, -tz, hw, hx, hy, hz)
        gqw += np.float64(g_dq[i, 0])
        gqx += np.float64(g_dq[i, 1])
        gqy += np.float64(g_dq[i, 2])
        gqz += np.float64(g_dq[i, 3])
        # τ = p − f(q), f = c + 2w (v × c) + 2 (v (v·c) − c (v·v)): g_f = −g_τ
        fx, fy, fz = -gtx, -gty, -gtz
        vxc_x = qy * cz - qz * cy
        vxc_y = qz * cx - qx * cz
        vxc_z = qx * cy - qy * cx
        gqw += 2.0 * (fx * vxc_x + fy * vxc_y + fz * vxc_z)
        # 2w (v × c): g_v += 2w (c × g)
        gqx += 2.0 * qw * (cy * fz - cz * fy)
        gqy += 2.0 * qw * (cz * fx - cx * fz)
        gqz += 2.0 * qw * (cx * fy - cy * fx)
        # 2 (v (v·c) − c (v·v)): g_v += 2 ((v·c) g + c (v·g) − 2 v (c·g))
        vc = qx * cx + qy * cy + qz * cz
        vg = qx * fx + qy * fy + qz * fz
        cg = cx * fx + cy * fy + cz * fz
        gqx += 2.0 * (vc * fx + cx * vg - 2.0 * qx * cg)
        gqy += 2.0 * (vc * fy + cy * vg - 2.0 * qy * cg)
        gqz += 2.0 * (vc * fz + cz * vg - 2.0 * qz * cg)
        # q = u / |u|
        if n2 > EPS:
            d = qw * gqw + qx * gqx + qy * gqy + qz * gqz
            guw, gux, guy, guz = (gqw - qw * d) / n2, (gqx - qx * d) / n2, (gqy - qy * d) / n2, (gqz - qz * d) / n2
        else:
            guw = gux = guy = guz = 0.0
        guw += np.float64(g_rot[i, 0])
        gux += np.float64(g_rot[i, 1])
        guy += np.float64(g_rot[i, 2])
        guz += np.float64(g_rot[i, 3])
        # u = r / |r|
        if n1 > EPS:
            d = uw * guw + ux * gux + uy * guy + uz * guz
            grw, grx, gry, grz = (guw - uw * d) / n1, (gux - ux * d) / n1, (guy - uy * d) / n1, (guz - uz * d) / n1
        else:
            grw = grx = gry = grz = 0.0
        gpx = np.float64(g_pos[i, 0]) - fx
        gpy = np.float64(g_pos[i, 1]) - fy
        gpz = np.float64(g_pos[i, 2]) - fz
        for k in range(S):
            bk = b[k]
            j = lo + k
            g_pk[i, j, 0] = bk * gpx
            g_pk[i, j, 1] = bk * gpy
            g_pk[i, j, 2] = bk * gpz
            g_rk[i, j, 0] = bk * grw
            g_rk[i, j, 1] = bk * grx
            g_rk[i, j, 2] = bk * gry
            g_rk[i, j, 3] = bk * grz


class _FusedNodeState(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pos_keys, rot_keys, lo, basis, centers):
        N = pos_keys.shape[0]
        b = basis.detach().double().cpu().numpy()
        c = _f32(centers)
        pos = np.empty((N, 3), np.float32)
        rot = np.empty((N, 4), np.float32)
        dq = np.empty((N, 8), np.float32)
        st = np.empty((N, 13))
        _forward(_f32(pos_keys), _f32(rot_keys), int(lo), b, c, pos, rot, dq, st)
        ctx.saved = (int(lo), b, c, st, tuple(pos_keys.shape), tuple(rot_keys.shape))
        ctx.dtypes = (pos_keys.dtype, rot_keys.dtype)
        return torch.from_numpy(pos), torch.from_numpy(rot), torch.from_numpy(dq)

    @staticmethod
    def backward(ctx, g_pos, g_rot, g_dq):
        lo, b, c, st, pshape, rshape = ctx.saved
        N = st.shape[0]
        z = lambda g, k: np.zeros((N, k), np.float32) if g is None else _f32(g)  # noqa: E731
        g_pk = np.zeros(pshape, np.float32)
        g_rk = np.zeros(rshape, np.float32)
        _backward(lo, b, c, st, z(g_pos, 3), z(g_rot, 4), z(g_dq, 8), g_pk, g_rk)
        return (torch.from_numpy(g_pk).to(ctx.dtypes[0]), torch.from_numpy(g_rk).to(ctx.dtypes[1]), None, None,
                None)


def fused_node_state(pos_keys: torch.Tensor, rot_keys: torch.Tensor, lo: int, basis: torch.Tensor,
                     centers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Node positions ``[N, 3]``, unit rotations ``[N, 4]`` and transforms ``[N, 8]`` at the time
    whose Catmull-Rom weights of keys ``lo .. lo + S - 1`` are ``basis [S]`` (see
    :meth:`engine.train.model.DynamicScene.spline_basis`); keys ``pos_keys [N, K, 3]``,
    ``rot_keys [N, K, 4]`` (differentiable), canonical centres ``centers [N, 3]``."""
    return _FusedNodeState.apply(pos_keys, rot_keys, lo, basis, centers)
