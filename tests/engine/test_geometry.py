"""The shared motion math: Hermite splines, quaternions, dual quaternions, binding, cameras."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from engine.geometry import binding, camera, dualquat, hermite, quaternion
from engine.geometry.blender_camera import blender_camera_from_intrinsics, blender_camera_intrinsics

DTYPES = [torch.float32, torch.float64]


# ---------------------------------------------------------------- Hermite
def _np_hermite(kt, keys, tans, t):
    """Independent float64 reference: loop over times, textbook basis."""
    out = np.zeros((keys.shape[0], len(t), keys.shape[-1]))
    for j, tt in enumerate(t):
        tt = min(max(tt, kt[0]), kt[-1])
        k = min(np.searchsorted(kt, tt, side="right") - 1, len(kt) - 2)
        dt = kt[k + 1] - kt[k]
        s = (tt - kt[k]) / dt
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        out[:, j] = h00 * keys[:, k] + h10 * dt * tans[:, k] + h01 * keys[:, k + 1] + h11 * dt * tans[:, k + 1]
    return out


@pytest.mark.parametrize("dtype", DTYPES)
def test_hermite_interpolates_keys_and_tangents(dtype):
    g = torch.Generator().manual_seed(0)
    kt = torch.tensor([0.0, 0.1, 0.45, 0.5, 1.0], dtype=dtype)
    keys = torch.randn(6, 5, 3, generator=g, dtype=dtype)
    tans = torch.randn(6, 5, 3, generator=g, dtype=dtype)
    v, d = hermite.hermite_eval(kt, keys, tans, kt, derivative=True)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(v, keys, atol=tol, rtol=0)
    torch.testing.assert_close(d, tans, atol=tol * 10, rtol=tol)


def test_hermite_matches_numpy_reference_and_clamps():
    rng = np.random.default_rng(1)
    kt = np.sort(rng.uniform(0, 1, 6))
    keys, tans = rng.normal(size=(4, 6, 3)), rng.normal(size=(4, 6, 3))
    t = np.concatenate([rng.uniform(-0.2, 1.2, 40), kt])
    ref = _np_hermite(kt, keys, tans, t)
    got = hermite.hermite_eval(torch.tensor(kt), torch.tensor(keys), torch.tensor(tans), torch.tensor(t))
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-12)
    outside = (t < kt[0]) | (t > kt[-1])
    assert outside.any()


def test_hermite_derivative_matches_finite_difference():
    kt = torch.tensor([0.0, 0.3, 0.7, 1.0], dtype=torch.float64)
    keys = torch.randn(2, 4, 3, dtype=torch.float64)
    tans = hermite.catmull_rom_tangents(kt, keys)
    t = torch.tensor([0.1, 0.35, 0.8], dtype=torch.float64)
    _, d = hermite.hermite_eval(kt, keys, tans, t, derivative=True)
    h = 1e-6
    fd = (hermite.hermite_eval(kt, keys, tans, t + h) - hermite.hermite_eval(kt, keys, tans, t - h)) / (2 * h)
    torch.testing.assert_close(d, fd, atol=1e-7, rtol=1e-6)


def test_broken_tangents_use_in_tangent_on_the_left():
    kt = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    keys = torch.zeros(1, 3, 1, dtype=torch.float64)
    t_out = torch.zeros_like(keys)
    t_in = torch.zeros_like(keys)
    t_in[0, 1, 0] = 1.0  # only the incoming tangent of the middle key
    _, d = hermite.hermite_eval(kt, keys, t_out, torch.tensor([0.999999, 1.5]), tangents_in=t_in, derivative=True)
    assert abs(float(d[0, 0, 0]) - 1.0) < 1e-4 and abs(float(d[0, 1, 0])) < 0.5


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 10.0), min_size=2, max_size=8, unique=True), st.integers(0, 2**31 - 1))
def test_hermite_properties_random_key_times(times, seed):
    kt = torch.tensor(sorted(times), dtype=torch.float64)
    gap = float((kt[1:] - kt[:-1]).min())
    if gap < 0.05:  # keys closer than this are not meaningful frames; avoids float cancellation
        return
    g = torch.Generator().manual_seed(seed)
    keys = torch.randn(3, len(kt), 2, generator=g, dtype=torch.float64)
    tans = hermite.catmull_rom_tangents(kt, keys)
    # interpolation
    torch.testing.assert_close(hermite.hermite_eval(kt, keys, tans, kt), keys, atol=1e-10, rtol=0)
    # C1 continuity at interior keys (eps small against the shortest interval's curvature)
    eps = 1e-6 * gap
    for k in range(1, len(kt) - 1):
        tl, tr = kt[k] - eps, kt[k] + eps
        vl, dl = hermite.hermite_eval(kt, keys, tans, tl.reshape(1), derivative=True)
        vr, dr = hermite.hermite_eval(kt, keys, tans, tr.reshape(1), derivative=True)
        torch.testing.assert_close(vl, vr, atol=1e-5, rtol=0)
        torch.testing.assert_close(dl, dr, atol=1e-3, rtol=1e-4)
    # constant extrapolation
    far = torch.tensor([kt[0] - 5.0, kt[-1] + 5.0], dtype=torch.float64)
    v = hermite.hermite_eval(kt, keys, tans, far)
    torch.testing.assert_close(v[:, 0], keys[:, 0])
    torch.testing.assert_close(v[:, 1], keys[:, -1])
    # basis matrix reproduces Catmull-Rom evaluation
    t = torch.rand(11, generator=g, dtype=torch.float64) * (kt[-1] - kt[0]) + kt[0]
    B = hermite.hermite_basis_matrix(kt, t)
    torch.testing.assert_close(torch.einsum("tk,nkc->ntc", B, keys), hermite.hermite_eval(kt, keys, tans, t))


def test_least_squares_fit_recovers_spline_from_noisy_samples_with_holes():
    g = torch.Generator().manual_seed(3)
    kt = torch.tensor([0.0, 0.2, 0.5, 0.8, 1.0], dtype=torch.float64)
    keys = torch.randn(10, 5, 3, generator=g, dtype=torch.float64)
    t = torch.linspace(0, 1, 400, dtype=torch.float64)
    clean = hermite.hermite_eval(kt, keys, hermite.catmull_rom_tangents(kt, keys), t)
    noisy = clean + 0.01 * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    holes = torch.rand(10, 400, generator=g) < 0.3
    noisy[holes] = float("nan")
    w = torch.rand(10, 400, generator=g, dtype=torch.float64) + 0.5
    fit = hermite.hermite_fit(kt, t, noisy, w)
    assert (fit - keys).abs().max() < 0.02
    # a curve with no samples returns the fallback; with few samples a smooth fit stays bounded
    empty = torch.full((1, 400, 3), float("nan"), dtype=torch.float64)
    fb = torch.ones(1, 5, 3, dtype=torch.float64)
    torch.testing.assert_close(hermite.hermite_fit(kt, t, empty, fallback=fb), fb)
    few = torch.full((1, 400, 3), float("nan"), dtype=torch.float64)
    few[0, 10] = 1.0
    few[0, 30] = 1.1
    smooth = hermite.hermite_fit(kt, t, few, smoothness=1.0)
    assert smooth.abs().max() < 2.0


# ---------------------------------------------------------------- quaternions & DQ
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


# ---------------------------------------------------------------- binding
def test_knn_matches_brute_force_and_chunking_is_invisible():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(3000, 3, generator=g)
    nodes = torch.randn(257, 3, generator=g)
    idx, d2 = binding.knn_nodes(pts, nodes, 5)
    brute = torch.cdist(pts.double(), nodes.double()) ** 2
    ref_d, ref_i = torch.topk(brute, 5, largest=False)
    torch.testing.assert_close(d2.double(), ref_d, atol=1e-4, rtol=1e-4)
    assert (idx == ref_i).float().mean() > 0.999  # ties aside
    idx2, d22 = binding.knn_nodes(pts, nodes, 5, chunk_size=77)
    assert torch.equal(idx, idx2) and torch.equal(d2, d22)


def test_rbf_weights_normalised_and_finite_far_away():
    nodes = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    radii = torch.tensor([0.1, 0.1, 0.2])
    pts = torch.tensor([[0.1, 0, 0], [1e4, 1e4, 0.0]])
    idx, w = binding.bind_gaussians(pts, nodes, radii, 3)
    assert torch.isfinite(w).all()
    torch.testing.assert_close(w.sum(-1), torch.ones(2))
    assert int(idx[0, 0]) == 0 and float(w[0, 0]) > 0.99
    # matches the paper's formula on a well-conditioned point
    d2 = ((pts[:1, None] - nodes[idx[:1]]) ** 2).sum(-1)
    raw = torch.exp(-d2 / (2 * radii[idx[:1]] ** 2))
    torch.testing.assert_close(w[:1], raw / raw.sum(-1, keepdim=True))


def test_knn_memory_bound_for_a_million_gaussians():
    chunk = binding.knn_chunk_size(5000, itemsize=4)
    temporaries = chunk * 5000 * 4 * 3
    assert temporaries <= binding.DEFAULT_MEMORY_BUDGET <= 2 * 1024**3
    assert chunk >= 1000  # still large chunks: few Python iterations for 1M points


# ---------------------------------------------------------------- cameras
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("with_dist", [False, True])
def test_project_unproject_round_trip(dtype, with_dist):
    g = torch.Generator().manual_seed(0)
    K = camera.intrinsics(300.0, 310.0, 160.3, 119.7, dtype=dtype)
    w2c = camera.look_at(torch.tensor([3.0, -4.0, 1.5], dtype=dtype), torch.zeros(3, dtype=dtype))
    x = torch.randn(500, 3, generator=g, dtype=dtype) * 0.5
    dist = torch.tensor([-0.12, 0.03, 0.001, -0.002, 0.0], dtype=dtype) if with_dist else None
    uv, z = camera.project(K, w2c, x, dist)
    assert (z > 0).all()
    back = camera.unproject(K, w2c, uv, z, dist)
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(back, x, atol=tol, rtol=0)


def test_look_at_is_opencv_and_blender_conversion_round_trips():
    eye = torch.tensor([0.0, -5.0, 0.0], dtype=torch.float64)
    w2c = camera.look_at(eye, torch.zeros(3, dtype=torch.float64))
    K = camera.intrinsics(100, 100, 50, 50)
    uv, z = camera.project(K, w2c, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert float(z[0]) == pytest.approx(5.0) and float(uv[0, 1]) < 50  # world up is image up (smaller v)
    M = camera.blender_matrix_world_from_w2c_opencv(w2c)
    torch.testing.assert_close(camera.w2c_opencv_from_blender_matrix_world(M), w2c)
    # a Blender camera looks down its local -z
    forward = -M[:3, 2]
    torch.testing.assert_close(forward, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


@pytest.mark.parametrize("fit,res,shift,aspect", [
    ("AUTO", (640, 360), (0.0, 0.0), (1.0, 1.0)),
    ("AUTO", (300, 500), (0.1, -0.05), (1.0, 1.0)),
    ("HORIZONTAL", (400, 300), (-0.2, 0.1), (1.0, 1.0)),
    ("VERTICAL", (400, 300), (0.05, 0.2), (1.0, 1.0)),
    ("AUTO", (400, 300), (0.1, 0.1), (2.0, 1.0)),
    ("VERTICAL", (320, 480), (0.0, 0.1), (1.0, 1.5)),
])
def test_blender_camera_intrinsics_match_blender(fit, res, shift, aspect):
    bpy = pytest.importorskip("bpy")
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("cam")
    cam_data.lens, cam_data.sensor_width, cam_data.sensor_height = 35.0, 36.0, 24.0
    cam_data.sensor_fit = fit
    cam_data.shift_x, cam_data.shift_y = shift
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.location = (0.3, -4.0, 1.0)
    cam.rotation_euler = (1.3, 0.1, 0.2)
    scene.render.resolution_x, scene.render.resolution_y = res
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    bpy.context.view_layer.update()
    fx, fy, cx, cy, w, h = blender_camera_intrinsics(cam_data.lens, 36.0, 24.0, fit, shift[0], shift[1], res[0],
                                                     res[1], aspect[0], aspect[1])
    K = camera.intrinsics(fx, fy, cx, cy)
    M = torch.tensor([list(r) for r in cam.matrix_world], dtype=torch.float64)
    w2c = camera.w2c_opencv_from_blender_matrix_world(M)
    rng = np.random.default_rng(0)
    for p in rng.normal(size=(8, 3)) * 0.7:
        ndc = world_to_camera_view(scene, cam, Vector(p.tolist()))
        expect = (ndc.x * w, (1 - ndc.y) * h)
        uv, _ = camera.project(K, w2c, torch.tensor(p[None]))
        np.testing.assert_allclose(uv[0].numpy(), expect, atol=1e-3)
    # and back again
    settings_ = blender_camera_from_intrinsics(fx, fy, cx, cy, w, h)
    again = blender_camera_intrinsics(settings_["lens"], settings_["sensor_width"], settings_["sensor_height"],
                                      settings_["sensor_fit"], settings_["shift_x"], settings_["shift_y"],
                                      settings_["res_x"], settings_["res_y"], settings_["pixel_aspect_x"],
                                      settings_["pixel_aspect_y"])
    np.testing.assert_allclose(again, (fx, fy, cx, cy, w, h), atol=1e-9)


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
