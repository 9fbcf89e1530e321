"""Fused CPU node regularisers: the ARAP, static-motion and spline-smoothness terms of the
training loss in Numba, each value computed together with its gradient.

The node graph is small (~1k nodes x 8 neighbours, ~12 keys) but its torch versions are
~150 tiny ops forward and as many in the backward -- about 6 ms of a ~60 ms step on two
cores, nearly all per-op overhead. Here each term is one serial pass in float64 (tens of
microseconds); the gradient is computed in the same pass (a scalar loss, so the backward
only scales it by the incoming gradient). Serial loops and float64 sums: the results do
not depend on the thread count. The torch versions stay the references (and the CUDA
path): :func:`engine.train.losses.arap_loss`, :func:`engine.train.losses.spline_smoothness`
and ``Objective.static_motion`` (``engine/train/objective.py``);
``tests/engine/test_fused_reg.py`` checks values and gradients against them.

arap(p0, q0, p1, q1, graph_idx)
    ``mean_ij |(p1_j − p1_i) − R_i (p0_j − p0_i)|²`` with ``R_i = R(q̂1_i) R(q̂0_i)ᵀ`` and
    ``q̂ = q / |q|``: the relative rotation of :func:`engine.train.losses.arap_loss` as the
    trainer builds it. Backward: ``∂/∂e1 = 2d``, ``∂/∂e0 = −2 R_iᵀ d``,
    ``∂/∂R_i = −2 Σ_j d_ij e0_ijᵀ`` split over ``A = R(q̂1)``, ``B = R(q̂0)`` as ``G B`` and
    ``Gᵀ A``, then through the rotation matrix and the normalisation.
key_regularisers(pos_keys, rot_keys, key_times, ...)
    The static-motion energy ``mean_i s_i (Var_k p_ik / extent² + arm_i Var_k q̂_ik)`` and the
    velocity / acceleration energies of ``pos_keys / extent`` (mean squared first / second
    divided differences in key-time units), in one pass over the keys.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ..raster.cpu import kernel_threads  # Numba at torch's thread count
from .fused import _f32  # float32 C-contiguous NumPy view (no copy for float32 tensors)

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
EPS = 1e-12  # quat_normalize's threshold


@njit(inline="always", **_JIT)
def _unit(q, i):
    """``(w, x, y, z, |q|)`` of ``q[i]`` normalised (identity when ``|q| <= EPS``)."""
    w, x, y, z = float(q[i, 0]), float(q[i, 1]), float(q[i, 2]), float(q[i, 3])
    n = np.sqrt(w * w + x * x + y * y + z * z)
    if n > EPS:
        return w / n, x / n, y / n, z / n, n
    return 1.0, 0.0, 0.0, 0.0, n


@njit(inline="always", **_JIT)
def _rot(w, x, y, z, R):
    """``R [3, 3]`` = rotation matrix of the unit quaternion ``(w, x, y, z)``."""
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(inline="always", **_JIT)
def _rot_backward(w, x, y, z, n, G, gq, i):
    """``gq[i] += ∂L/∂q`` for ``R = R(q / n)`` given ``G = ∂L/∂R [3, 3]`` (through the
    rotation matrix, then the normalisation: ``(g − q̂ (q̂·g)) / n``; none when ``n <= EPS``,
    where the normalised quaternion is a constant)."""
    gw = 2 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
    gx = 2 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
              + w * G[2, 1] - 2 * x * G[2, 2])
    gy = 2 * (-2 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
              + z * G[2, 1] - 2 * y * G[2, 2])
    gz = 2 * (-2 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2 * z * G[1, 1] + y * G[1, 2]
              + x * G[2, 0] + y * G[2, 1])
    if n > EPS:
        dot = w * gw + x * gx + y * gy + z * gz
        gq[i, 0] += (gw - w * dot) / n
        gq[i, 1] += (gx - x * dot) / n
        gq[i, 2] += (gy - y * dot) / n
        gq[i, 3] += (gz - z * dot) / n


@njit(inline="always", **_JIT)
def _edge_grad(g, i, j, x, y, z):
    """An edge ``e = p_j − p_i`` with gradient ``(x, y, z)``: add it to ``g[j]``, subtract from ``g[i]``."""
    g[j, 0] += x
    g[j, 1] += y
    g[j, 2] += z
    g[i, 0] -= x
    g[i, 1] -= y
    g[i, 2] -= z


@njit(**_JIT)
def _arap(p0, q0, p1, q1, gidx, g_p0, g_q0, g_p1, g_q1):
    """ARAP value (mean over the ``N·k`` edges) with its gradients written to the float64
    ``g_* [N, 3|4]`` (zeroed here). Inputs: p0, p1 [N, 3]; q0, q1 [N, 4]; gidx [N, k]."""
    N, k = gidx.shape
    g_p0[:] = 0.0
    g_q0[:] = 0.0
    g_p1[:] = 0.0
    g_q1[:] = 0.0
    if N == 0 or k == 0:
        return 0.0
    c = 1.0 / (N * k)
    A = np.empty((3, 3))
    B = np.empty((3, 3))
    R = np.empty((3, 3))
    G = np.empty((3, 3))
    GA = np.empty((3, 3))
    GB = np.empty((3, 3))
    total = 0.0
    for i in range(N):
        w1, x1, y1, z1, n1 = _unit(q1, i)
        w0, x0, y0, z0, n0 = _unit(q0, i)
        _rot(w1, x1, y1, z1, A)
        _rot(w0, x0, y0, z0, B)
        for r in range(3):
            for s in range(3):
                R[r, s] = A[r, 0] * B[s, 0] + A[r, 1] * B[s, 1] + A[r, 2] * B[s, 2]  # A Bᵀ
        G[:] = 0.0
        for jj in range(k):
            j = gidx[i, jj]
            e0x = float(p0[j, 0]) - float(p0[i, 0])
            e0y = float(p0[j, 1]) - float(p0[i, 1])
            e0z = float(p0[j, 2]) - float(p0[i, 2])
            dx = float(p1[j, 0]) - float(p1[i, 0]) - (R[0, 0] * e0x + R[0, 1] * e0y + R[0, 2] * e0z)
            dy = float(p1[j, 1]) - float(p1[i, 1]) - (R[1, 0] * e0x + R[1, 1] * e0y + R[1, 2] * e0z)
            dz = float(p1[j, 2]) - float(p1[i, 2]) - (R[2, 0] * e0x + R[2, 1] * e0y + R[2, 2] * e0z)
            total += dx * dx + dy * dy + dz * dz
            gx, gy, gz = 2 * c * dx, 2 * c * dy, 2 * c * dz  # ∂/∂e1 = ∂/∂d; ∂/∂r = −that
            _edge_grad(g_p1, i, j, gx, gy, gz)
            # ∂/∂e0 = Rᵀ ∂/∂r = −Rᵀ g
            ex = -(R[0, 0] * gx + R[1, 0] * gy + R[2, 0] * gz)
            ey = -(R[0, 1] * gx + R[1, 1] * gy + R[2, 1] * gz)
            ez = -(R[0, 2] * gx + R[1, 2] * gy + R[2, 2] * gz)
            _edge_grad(g_p0, i, j, ex, ey, ez)
            # ∂/∂R += (∂/∂r) e0ᵀ
            G[0, 0] -= gx * e0x
            G[0, 1] -= gx * e0y
            G[0, 2] -= gx * e0z
            G[1, 0] -= gy * e0x
            G[1, 1] -= gy * e0y
            G[1, 2] -= gy * e0z
            G[2, 0] -= gz * e0x
            G[2, 1] -= gz * e0y
            G[2, 2] -= gz * e0z
        # R = A Bᵀ: ∂/∂A = G B, ∂/∂B = Gᵀ A
        for r in range(3):
            for s in range(3):
                GA[r, s] = G[r, 0] * B[0, s] + G[r, 1] * B[1, s] + G[r, 2] * B[2, s]
                GB[r, s] = G[0, r] * A[0, s] + G[1, r] * A[1, s] + G[2, r] * A[2, s]
        _rot_backward(w1, x1, y1, z1, n1, GA, g_q1, i)
        _rot_backward(w0, x0, y0, z0, n0, GB, g_q0, i)
    return total * c


@njit(inline="always", **_JIT)
def _minus(ref, i, kk, w, a, b, c):
    """``(w, a, b, c) − ref[i, kk]`` (a 4-vector, in float64)."""
    return (w - float(ref[i, kk, 0]), a - float(ref[i, kk, 1]), b - float(ref[i, kk, 2]),
            c - float(ref[i, kk, 3]))


@njit(inline="always", **_JIT)
def _pos_key(pk, ref_p, has_ref, i, kk):
    """Position key ``pk[i, kk]`` minus the reference when there is one (float64)."""
    x0, x1, x2 = float(pk[i, kk, 0]), float(pk[i, kk, 1]), float(pk[i, kk, 2])
    if has_ref:
        x0 -= float(ref_p[i, kk, 0])
        x1 -= float(ref_p[i, kk, 1])
        x2 -= float(ref_p[i, kk, 2])
    return x0, x1, x2


@njit(parallel=True, **_JIT)
def _key_terms(pk, rk, kt, s, arm, ref_p, ref_q, inv_ext, g_st_p, g_st_q, g_vel, g_acc, part):
    """``(static, velocity, acceleration)`` of keys ``pk [N, K, 3]``, ``rk [N, K, 4]`` at
    key times ``kt [K]``, with their gradients in the float64 ``g_st_p [N,K,3]``,
    ``g_st_q [N,K,4]`` (static w.r.t. pos / rot keys), ``g_vel``, ``g_acc [N,K,3]``.

    ``s, arm [N]``: static weights and rotation arms; ``ref_p [N,K,3]``, ``ref_q [N,K,4]``
    (already scaled by ``static_init`` and normalised) are subtracted before the variance,
    or empty arrays for none. ``inv_ext`` = 1 / scene extent. ``part [N, 3]`` float64
    scratch: per-node sums, added up serially at the end (a fixed order, so the result
    does not depend on the thread count). prange over nodes: every node writes only its
    own rows."""
    N, K = pk.shape[0], pk.shape[1]
    if N == 0 or K == 0:
        g_st_p[:] = 0.0
        g_st_q[:] = 0.0
        g_vel[:] = 0.0
        g_acc[:] = 0.0
        return 0.0, 0.0, 0.0
    has_ref = ref_p.shape[0] == N
    inv_k = 1.0 / K
    inv_n = 1.0 / N  # the static term is a mean over the nodes
    nv = K - 1 if K >= 2 else 0
    na = K - 2 if K >= 3 else 0
    inv_dt = np.empty(max(nv, 1))
    inv_dtm = np.empty(max(na, 1))
    for kk in range(nv):
        inv_dt[kk] = 1.0 / max(float(kt[kk + 1]) - float(kt[kk]), 1e-6)
    for kk in range(na):
        inv_dtm[kk] = 1.0 / (0.5 * (1.0 / inv_dt[kk] + 1.0 / inv_dt[kk + 1]))
    cv = 2.0 / (N * nv * 3) if nv else 0.0  # ∂ mean(vel²) / ∂vel = cv vel
    ca = 2.0 / (N * na * 3) if na else 0.0
    for i in prange(N):
        # --- static: variance over the keys of the position and of the normalised rotation
        # (pass 1: means; the normalised rotations go to g_st_q as scratch)
        mp0 = mp1 = mp2 = 0.0
        mq0 = mq1 = mq2 = mq3 = 0.0
        for kk in range(K):
            w, a, b, c = float(rk[i, kk, 0]), float(rk[i, kk, 1]), float(rk[i, kk, 2]), float(rk[i, kk, 3])
            n = np.sqrt(w * w + a * a + b * b + c * c)
            if n > EPS:
                r = 1.0 / n
                w, a, b, c = w * r, a * r, b * r, c * r
            else:
                w, a, b, c = 1.0, 0.0, 0.0, 0.0
            g_st_q[i, kk, 0], g_st_q[i, kk, 1], g_st_q[i, kk, 2], g_st_q[i, kk, 3] = w, a, b, c
            if has_ref:
                w, a, b, c = _minus(ref_q, i, kk, w, a, b, c)
            mq0 += w
            mq1 += a
            mq2 += b
            mq3 += c
            x0, x1, x2 = _pos_key(pk, ref_p, has_ref, i, kk)
            mp0 += x0
            mp1 += x1
            mp2 += x2
        mp0, mp1, mp2 = mp0 * inv_k, mp1 * inv_k, mp2 * inv_k
        mq0, mq1, mq2, mq3 = mq0 * inv_k, mq1 * inv_k, mq2 * inv_k, mq3 * inv_k
        # pass 2: energies and gradients; ∂Var/∂x_k = 2 (x_k − mean) / K (the mean's own
        # term sums to zero)
        cp = 2.0 * s[i] * inv_k * inv_ext * inv_n
        cq = 2.0 * s[i] * arm[i] * inv_k * inv_n
        ep = 0.0
        eq = 0.0
        for kk in range(K):
            x0, x1, x2 = _pos_key(pk, ref_p, has_ref, i, kk)
            d0, d1, d2 = (x0 - mp0) * inv_ext, (x1 - mp1) * inv_ext, (x2 - mp2) * inv_ext
            ep += d0 * d0 + d1 * d1 + d2 * d2
            g_st_p[i, kk, 0] = cp * d0
            g_st_p[i, kk, 1] = cp * d1
            g_st_p[i, kk, 2] = cp * d2
            w, a, b, c = g_st_q[i, kk, 0], g_st_q[i, kk, 1], g_st_q[i, kk, 2], g_st_q[i, kk, 3]
            e0, e1, e2, e3 = w - mq0, a - mq1, b - mq2, c - mq3
            if has_ref:
                e0, e1, e2, e3 = _minus(ref_q, i, kk, e0, e1, e2, e3)
            eq += e0 * e0 + e1 * e1 + e2 * e2 + e3 * e3
            q0, q1, q2, q3 = float(rk[i, kk, 0]), float(rk[i, kk, 1]), float(rk[i, kk, 2]), float(rk[i, kk, 3])
            n = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
            if n > EPS:  # through q̂ = q / |q|: (g − q̂ (q̂·g)) / |q|
                g0, g1, g2, g3 = cq * e0, cq * e1, cq * e2, cq * e3
                dot = w * g0 + a * g1 + b * g2 + c * g3
                r = 1.0 / n
                g_st_q[i, kk, 0] = (g0 - w * dot) * r
                g_st_q[i, kk, 1] = (g1 - a * dot) * r
                g_st_q[i, kk, 2] = (g2 - b * dot) * r
                g_st_q[i, kk, 3] = (g3 - c * dot) * r
            else:  # the identity: a constant
                g_st_q[i, kk, 0] = g_st_q[i, kk, 1] = g_st_q[i, kk, 2] = g_st_q[i, kk, 3] = 0.0
        part[i, 0] = s[i] * (ep + arm[i] * eq) * inv_k
        # --- velocity / acceleration of pk / extent (no reference)
        vs = 0.0
        acs = 0.0
        for kk in range(K):
            for d in range(3):
                g_vel[i, kk, d] = 0.0
                g_acc[i, kk, d] = 0.0
        for d in range(3):
            v_prev = 0.0
            for kk in range(nv):
                v = (float(pk[i, kk + 1, d]) - float(pk[i, kk, d])) * inv_ext * inv_dt[kk]
                vs += v * v
                gv = cv * v * inv_dt[kk] * inv_ext
                g_vel[i, kk + 1, d] += gv
                g_vel[i, kk, d] -= gv
                if kk >= 1:  # acc[kk-1] = (vel[kk] − vel[kk-1]) / dtm[kk-1]
                    acc = (v - v_prev) * inv_dtm[kk - 1]
                    acs += acc * acc
                    ga = ca * acc * inv_dtm[kk - 1]  # ∂/∂vel[kk] = ga, ∂/∂vel[kk-1] = −ga
                    g1 = ga * inv_dt[kk] * inv_ext
                    g0 = ga * inv_dt[kk - 1] * inv_ext
                    g_acc[i, kk + 1, d] += g1
                    g_acc[i, kk, d] -= g1 + g0
                    g_acc[i, kk - 1, d] += g0
                v_prev = v
        part[i, 1] = vs
        part[i, 2] = acs
    static = 0.0
    vel_sum = 0.0
    acc_sum = 0.0
    for i in range(N):
        static += part[i, 0]
        vel_sum += part[i, 1]
        acc_sum += part[i, 2]
    return static * inv_n, vel_sum * cv * 0.5, acc_sum * ca * 0.5


class _FusedARAP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, p0, q0, p1, q1, graph_idx):
        gp0, gq0 = np.empty((p0.shape[0], 3)), np.empty((p0.shape[0], 4))
        gp1, gq1 = np.empty((p0.shape[0], 3)), np.empty((p0.shape[0], 4))
        gidx = graph_idx.detach().to(torch.int64).contiguous().numpy()
        val = _arap(_f32(p0), _f32(q0), _f32(p1), _f32(q1), gidx, gp0, gq0, gp1, gq1)
        ctx.grads = (gp0, gq0, gp1, gq1)
        ctx.dtypes = (p0.dtype, q0.dtype, p1.dtype, q1.dtype)
        return p0.new_tensor(val)

    @staticmethod
    def backward(ctx, g):
        gs = float(g)
        out = tuple(torch.from_numpy(a * gs).to(dt) for a, dt in zip(ctx.grads, ctx.dtypes))
        return out + (None,)


class _FusedKeyTerms(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pos_keys, rot_keys, key_times, s, arm, ref_p, ref_q, inv_ext):
        N, K = pos_keys.shape[:2]
        g_st_p, g_st_q = np.empty((N, K, 3)), np.empty((N, K, 4))
        g_vel, g_acc = np.empty((N, K, 3)), np.empty((N, K, 3))
        empty = np.zeros((0, 0, 0), np.float32)
        with kernel_threads():
            st, vel, acc = _key_terms(_f32(pos_keys), _f32(rot_keys), _f32(key_times),
                                      s.detach().double().cpu().numpy(), arm.detach().double().cpu().numpy(),
                                      empty if ref_p is None else _f32(ref_p),
                                      empty if ref_q is None else _f32(ref_q), float(inv_ext), g_st_p, g_st_q, g_vel,
                                      g_acc, np.empty((N, 3)))
        ctx.grads = (g_st_p, g_st_q, g_vel, g_acc)
        ctx.dtypes = (pos_keys.dtype, rot_keys.dtype)
        return pos_keys.new_tensor(st), pos_keys.new_tensor(vel), pos_keys.new_tensor(acc)

    @staticmethod
    def backward(ctx, g_static, g_vel, g_acc):
        gp_st, gq_st, gp_vel, gp_acc = ctx.grads
        a, b, c = (0.0 if x is None else float(x) for x in (g_static, g_vel, g_acc))
        gp = torch.from_numpy(a * gp_st + b * gp_vel + c * gp_acc).to(ctx.dtypes[0])
        gq = torch.from_numpy(a * gq_st).to(ctx.dtypes[1])
        return gp, gq, None, None, None, None, None, None


def fused_arap(p0: torch.Tensor, q0: torch.Tensor, p1: torch.Tensor, q1: torch.Tensor,
               graph_idx: torch.Tensor) -> torch.Tensor:
    """ARAP between two node states (see the module docstring): ``p0, p1 [N, 3]``,
    ``q0, q1 [N, 4]`` (normalised inside), ``graph_idx [N, k]``; a scalar, differentiable
    in the four states. Equals ``arap_loss(p0, p1, R(q̂1) R(q̂0)ᵀ, graph_idx)``."""
    return _FusedARAP.apply(p0, q0, p1, q1, graph_idx)


def fused_key_terms(pos_keys: torch.Tensor, rot_keys: torch.Tensor, key_times: torch.Tensor, s: torch.Tensor,
                    arm: torch.Tensor, extent: float, ref_pos: torch.Tensor | None = None,
                    ref_rot: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(static, velocity, acceleration)`` of the keys ``pos_keys [N, K, 3]``,
    ``rot_keys [N, K, 4]`` at ``key_times [K]`` (see the module docstring); differentiable
    in both keys. ``s, arm [N]`` are constants; ``ref_pos [N, K, 3]`` / ``ref_rot [N, K, 4]``
    (optional, constants) are subtracted from the keys / normalised rotations before the
    variance."""
    return _FusedKeyTerms.apply(pos_keys, rot_keys, key_times, s, arm, ref_pos, ref_rot, 1.0 / float(extent))


def fused_reg_available(*tensors: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" for t in tensors)
