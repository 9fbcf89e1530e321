"""Quaternions and dual quaternions (engine/geometry/quaternion.py, dualquat.py), incl. a numpy DQB reference."""

import math

import numpy as np
import pytest
import torch

from engine.geometry import dualquat, quaternion

DTYPES = [torch.float32, torch.float64]


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


def _rand_quats(n, g, dtype=torch.float64):
    return quaternion.quat_normalize(torch.randn(n, 4, generator=g, dtype=dtype))


def test_quaternion_matrix_round_trip_and_apply():
    g = torch.Generator().manual_seed(0)
    q = _rand_quats(200, g)
    R = quaternion.quat_to_matrix(q)
    q2 = quaternion.quat_from_matrix(R)
    torch.testing.assert_close(q2, torch.where(q[:, :1] < 0, -q, q), atol=1e-10, rtol=0)
    v = torch.randn(200, 3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(quaternion.quat_apply(q, v), (R @ v.unsqueeze(-1)).squeeze(-1))
    # product composes rotations
    p = _rand_quats(200, g)
    torch.testing.assert_close(quaternion.quat_to_matrix(quaternion.quat_mul(p, q)), quaternion.quat_to_matrix(p) @ R)


def _np_dqb(R, t, idx, w):
    """Independent float64 numpy DQB (Kavan 2007) returning blended (R, t)."""
    def mat2q(M):
        w_ = math.sqrt(max(0.0, 1 + M[0, 0] + M[1, 1] + M[2, 2])) / 2
        x = math.copysign(math.sqrt(max(0.0, 1 + M[0, 0] - M[1, 1] - M[2, 2])) / 2, M[2, 1] - M[1, 2])
        y = math.copysign(math.sqrt(max(0.0, 1 - M[0, 0] + M[1, 1] - M[2, 2])) / 2, M[0, 2] - M[2, 0])
        z = math.copysign(math.sqrt(max(0.0, 1 - M[0, 0] - M[1, 1] + M[2, 2])) / 2, M[1, 0] - M[0, 1])
        return np.array([w_, x, y, z])

    def qmul(a, b):
        return np.array([a[0] * b[0] - a[1:] @ b[1:], *(a[0] * b[1:] + b[0] * a[1:] + np.cross(a[1:], b[1:]))])

    Rs, ts = [], []
    for i in range(idx.shape[0]):
        qs = [mat2q(R[j]) for j in idx[i]]
        ds = [0.5 * qmul(np.array([0, *t[j]]), q) for j, q in zip(idx[i], qs)]
        piv = int(np.argmax(w[i]))
        real, dual = np.zeros(4), np.zeros(4)
        for k in range(len(qs)):
            s = 1.0 if qs[k] @ qs[piv] >= 0 else -1.0
            real += w[i, k] * s * qs[k]
            dual += w[i, k] * s * ds[k]
        n = np.linalg.norm(real)
        real, dual = real / n, dual / n
        tt = 2 * qmul(dual, real * np.array([1, -1, -1, -1]))[1:]
        ww, x, y, z = real
        Rm = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - ww * z), 2 * (x * z + ww * y)],
                       [2 * (x * y + ww * z), 1 - 2 * (x * x + z * z), 2 * (y * z - ww * x)],
                       [2 * (x * z - ww * y), 2 * (y * z + ww * x), 1 - 2 * (x * x + y * y)]])
        Rs.append(Rm)
        ts.append(tt)
    return np.array(Rs), np.array(ts)


def test_rotation_vector_round_trip_matches_scipy():
    from scipy.spatial.transform import Rotation

    v = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 1e-9, 0.0]], dtype=torch.float64)
    q = quaternion.quat_from_axis_angle(v, v.norm(dim=-1))
    torch.testing.assert_close(quaternion.quat_to_rotation_vector(q), v)
    torch.testing.assert_close(quaternion.quat_to_rotation_vector(-q), v)  # the other sign, one rotation
    R = Rotation.random(16, random_state=0)
    got = quaternion.quat_to_rotation_vector(quaternion.quat_from_matrix(torch.as_tensor(R.as_matrix())))
    np.testing.assert_allclose(got.numpy(), R.as_rotvec(), atol=1e-10)


def test_dq_blend_identical_transforms_returns_that_transform():
    g = torch.Generator().manual_seed(1)
    q = _rand_quats(1, g)
    t = torch.randn(1, 3, generator=g, dtype=torch.float64)
    dq = dualquat.dq_from_rt(q, t).expand(5, 8)
    idx = torch.randint(0, 5, (30, 4), generator=g)
    w = torch.softmax(torch.randn(30, 4, generator=g, dtype=torch.float64), -1)
    # flip some signs: the same rotation written as -q must not change the result
    dq = dq.clone()
    dq[::2] = -dq[::2]
    out = dualquat.dq_blend(dq, idx, w)
    T = dualquat.dq_to_se3(out)
    T0 = dualquat.dq_to_se3(dualquat.dq_from_rt(q, t))
    torch.testing.assert_close(T, T0.expand(30, 4, 4), atol=1e-12, rtol=0)


def test_dq_blend_is_rigid_and_matches_numpy_reference():
    g = torch.Generator().manual_seed(2)
    n, G, K = 12, 200, 4
    q = _rand_quats(n, g)
    q[::3] = -q[::3]  # antipodal representatives
    t = torch.randn(n, 3, generator=g, dtype=torch.float64)
    idx = torch.randint(0, n, (G, K), generator=g)
    w = torch.softmax(torch.randn(G, K, generator=g, dtype=torch.float64), -1)
    T = dualquat.dq_to_se3(dualquat.dq_blend(dualquat.dq_from_rt(q, t), idx, w))
    R = T[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(G, 3, 3),
                               atol=1e-12, rtol=0)
    assert torch.allclose(torch.linalg.det(R), torch.ones(G, dtype=torch.float64))
    R_ref, t_ref = _np_dqb(quaternion.quat_to_matrix(q).numpy(), t.numpy(), idx.numpy(), w.numpy())
    np.testing.assert_allclose(R.numpy(), R_ref, atol=1e-6)
    np.testing.assert_allclose(T[:, :3, 3].numpy(), t_ref, atol=1e-6)


def test_se3_round_trip_and_node_transform_contract():
    g = torch.Generator().manual_seed(4)
    q = _rand_quats(20, g)
    T = torch.eye(4, dtype=torch.float64).repeat(20, 1, 1)
    T[:, :3, :3] = quaternion.quat_to_matrix(q)
    T[:, :3, 3] = torch.randn(20, 3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(dualquat.dq_to_se3(dualquat.dq_from_se3(T)), T)
    c = torch.randn(20, 3, generator=g, dtype=torch.float64)
    p = torch.randn(20, 3, generator=g, dtype=torch.float64)
    x = torch.randn(20, 3, generator=g, dtype=torch.float64)
    dq = dualquat.node_transforms_dq(c, p, q)
    expect = (quaternion.quat_to_matrix(q) @ (x - c).unsqueeze(-1)).squeeze(-1) + p
    torch.testing.assert_close(dualquat.dq_apply_points(dq, x), expect)
    # inverse undoes it
    torch.testing.assert_close(dualquat.dq_apply_points(dualquat.dq_inverse(dq), expect), x)


@pytest.mark.parametrize("dtype", DTYPES)
def test_dq_apply_rotations_composes(dtype):
    g = torch.Generator().manual_seed(5)
    q = _rand_quats(10, g, dtype)
    qg = _rand_quats(10, g, dtype)
    dq = dualquat.dq_from_rt(q, torch.zeros(10, 3, dtype=dtype))
    R = quaternion.quat_to_matrix(dualquat.dq_apply_rotations(dq, qg))
    torch.testing.assert_close(R, quaternion.quat_to_matrix(q) @ quaternion.quat_to_matrix(qg),
                               atol=1e-5 if dtype == torch.float32 else 1e-12, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_geometry_on_cuda():
    g = torch.Generator().manual_seed(0)
    q = _rand_quats(50, g).cuda()
    t = torch.randn(50, 3, dtype=torch.float64).cuda()
    idx = torch.randint(0, 50, (100, 4)).cuda()
    w = torch.full((100, 4), 0.25, dtype=torch.float64).cuda()
    out = dualquat.dq_blend(dualquat.dq_from_rt(q, t), idx, w)
    ref = dualquat.dq_blend(dualquat.dq_from_rt(q.cpu(), t.cpu()), idx.cpu(), w.cpu())
    torch.testing.assert_close(out.cpu(), ref)


def test_dq_blend_batched_over_times_matches_per_time_blend():
    g = torch.Generator().manual_seed(6)
    T_, n, G, K = 3, 9, 40, 4
    q = quaternion.quat_normalize(torch.randn(T_, n, 4, generator=g, dtype=torch.float64))
    t = torch.randn(T_, n, 3, generator=g, dtype=torch.float64)
    c = torch.randn(n, 3, generator=g, dtype=torch.float64)
    idx = torch.randint(0, n, (G, K), generator=g)
    w = torch.softmax(torch.randn(G, K, generator=g, dtype=torch.float64), -1)
    x = torch.randn(G, 3, generator=g, dtype=torch.float64)
    batched = dualquat.dq_blend(dualquat.dq_from_rt(q, t), idx, w)
    assert batched.shape == (T_, G, 8)
    moved = dualquat.deform_points(c, t, q, idx, w, x)  # [T, G, 3], x broadcast over time
    for i in range(T_):
        torch.testing.assert_close(batched[i], dualquat.dq_blend(dualquat.dq_from_rt(q[i], t[i]), idx, w))
        torch.testing.assert_close(moved[i], dualquat.deform_points(c, t[i], q[i], idx, w, x))


def test_dq_mul_composes_like_matrices_and_quat_from_matrix_is_robust():
    g = torch.Generator().manual_seed(7)
    qa, qb = _rand_quats(30, g), _rand_quats(30, g)
    ta, tb = torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
    Ta = dualquat.dq_to_se3(dualquat.dq_from_rt(qa, ta))
    Tb = dualquat.dq_to_se3(dualquat.dq_from_rt(qb, tb))
    ab = dualquat.dq_mul(dualquat.dq_from_rt(qa, ta), dualquat.dq_from_rt(qb, tb))
    torch.testing.assert_close(dualquat.dq_to_se3(ab), Ta @ Tb)
    # half-turns (w = 0, where naive trace-based extraction divides by ~0) and tiny angles
    axis = torch.randn(30, 3, generator=g, dtype=torch.float64)
    angle = torch.cat([torch.full((10,), math.pi), torch.full((10,), math.pi - 1e-9), torch.full((10,), 1e-9)])
    angle = angle.to(torch.float64)
    q = quaternion.quat_from_axis_angle(axis, angle)
    back = quaternion.quat_from_matrix(quaternion.quat_to_matrix(q))
    assert (back[:, 0] >= 0).all()
    torch.testing.assert_close(quaternion.quat_to_matrix(back), quaternion.quat_to_matrix(q), atol=1e-12, rtol=0)
    # same rotation up to sign
    assert torch.allclose((back * q).sum(-1).abs(), torch.ones(30, dtype=torch.float64), atol=1e-12)
    # quat_apply broadcasts a single rotation over many vectors and vice versa
    v = torch.randn(5, 3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(quaternion.quat_apply(q[0], v), v @ quaternion.quat_to_matrix(q[0]).T)
    torch.testing.assert_close(quaternion.quat_apply(q[:5], v[0]),
                               (quaternion.quat_to_matrix(q[:5]) @ v[0]))
