"""Hermite splines (engine/geometry/hermite.py): evaluation, tangents, basis matrix, LSQ fit."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from engine.geometry import hermite

DTYPES = [torch.float32, torch.float64]


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


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


@settings(max_examples=60, deadline=None)
@given(st.floats(-5.0, 5.0), st.lists(st.floats(0.01, 3.0), min_size=1, max_size=7), st.integers(0, 2**31 - 1))
def test_hermite_properties_random_key_times(start, gaps, seed):
    # strictly increasing, non-uniform key times built from random positive gaps
    kt = start + torch.cumsum(torch.tensor([0.0] + gaps, dtype=torch.float64), 0)
    g = torch.Generator().manual_seed(seed)
    keys = torch.randn(3, len(kt), 2, generator=g, dtype=torch.float64)
    tans = hermite.catmull_rom_tangents(kt, keys)
    # interpolation of values and (Catmull-Rom) tangents at every key
    v, d = hermite.hermite_eval(kt, keys, tans, kt, derivative=True)
    torch.testing.assert_close(v, keys, atol=1e-10, rtol=0)
    torch.testing.assert_close(d, tans, atol=1e-8, rtol=1e-8)
    # C1 continuity at interior keys: the left segment's end (evaluated on the spline cut
    # after key k, whose last segment is segment k-1 at tau=1) equals the right segment's
    # start (spline cut before key k) in value and derivative -- exact, no finite epsilon.
    for k in range(1, len(kt) - 1):
        at = kt[k].reshape(1)
        vl, dl = hermite.hermite_eval(kt[:k + 1], keys[:, :k + 1], tans[:, :k + 1], at, derivative=True)
        vr, dr = hermite.hermite_eval(kt[k:], keys[:, k:], tans[:, k:], at, derivative=True)
        torch.testing.assert_close(vl, vr, atol=1e-10, rtol=0)
        torch.testing.assert_close(dl, dr, atol=1e-8, rtol=1e-8)
    # inside the range the full spline agrees with the independent numpy evaluation
    t = kt[0] + (kt[-1] - kt[0]) * torch.rand(13, generator=g, dtype=torch.float64)
    np.testing.assert_allclose(hermite.hermite_eval(kt, keys, tans, t).numpy(),
                               _np_hermite(kt.numpy(), keys.numpy(), tans.numpy(), t.numpy()), atol=1e-9)
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


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_hermite_device_and_dtype_agnostic(device, dtype):
    g = torch.Generator().manual_seed(5)
    kt = torch.tensor([0.0, 0.3, 0.45, 1.0], dtype=dtype)
    keys = torch.randn(6, 4, 3, generator=g, dtype=dtype)
    t = torch.rand(9, generator=g, dtype=dtype) * 1.2 - 0.1
    tans = hermite.catmull_rom_tangents(kt, keys)
    ref_v, ref_d = hermite.hermite_eval(kt, keys, tans, t, derivative=True)
    v, d = hermite.hermite_eval(kt.to(device), keys.to(device), tans.to(device), t.to(device), derivative=True)
    assert v.dtype == dtype and v.device.type == device and d.shape == (6, 9, 3)
    torch.testing.assert_close(v.cpu(), ref_v)
    torch.testing.assert_close(d.cpu(), ref_d)
    q = hermite.hermite_eval_quat(kt.to(device), keys.to(device), tans.to(device), t.to(device))
    torch.testing.assert_close(q.norm(dim=-1).cpu(), torch.ones(6, 9, dtype=dtype))
    # the fit runs on the device too and reproduces exact (noise-free) Catmull-Rom data
    ts = torch.linspace(0, 1, 50, dtype=dtype)
    clean = hermite.hermite_eval(kt, keys, tans, ts)
    fit = hermite.hermite_fit(kt.to(device), ts.to(device), clean.to(device), ridge=0.0)  # no bias: exact
    tol = 1e-3 if dtype == torch.float32 else 1e-6
    torch.testing.assert_close(fit.cpu(), keys, atol=tol, rtol=0)


def test_hermite_is_differentiable_wrt_keys_and_tangents():
    kt = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    keys = torch.randn(2, 3, 2, dtype=torch.float64, requires_grad=True)
    tans = torch.randn(2, 3, 2, dtype=torch.float64, requires_grad=True)
    t = torch.tensor([0.1, 0.6, 0.9], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda k, m: hermite.hermite_eval(kt, k, m, t), (keys, tans))


def test_fit_weights_ignore_outliers_and_smoothness_holds_unobserved_keys_still():
    g = torch.Generator().manual_seed(8)
    kt = torch.linspace(0, 1, 6, dtype=torch.float64)
    keys = torch.randn(4, 6, 2, generator=g, dtype=torch.float64)
    t = torch.linspace(0, 1, 120, dtype=torch.float64)
    clean = hermite.hermite_eval(kt, keys, hermite.catmull_rom_tangents(kt, keys), t)
    corrupt = clean.clone()
    bad = torch.rand(4, 120, generator=g) < 0.2
    corrupt[bad] += 50.0
    w = (~bad).to(torch.float64)  # zero weight on the outliers
    fit = hermite.hermite_fit(kt, t, corrupt, w, ridge=0.0)
    torch.testing.assert_close(fit, keys, atol=1e-8, rtol=0)
    assert (hermite.hermite_fit(kt, t, corrupt) - keys).abs().max() > 1.0  # the weights mattered
    # observed only early on, with a trend: smoothness keeps the unobserved keys near the
    # last observed value instead of extrapolating the trend (or exploding)
    early = torch.full((1, 120, 1), float("nan"), dtype=torch.float64)
    early[0, :15, 0] = 3.0 * t[:15]  # rises to ~0.35 by t=0.12
    free = hermite.hermite_fit(kt, t, early, smoothness=0.0)
    still = hermite.hermite_fit(kt, t, early, smoothness=1.0)
    assert torch.isfinite(still).all()
    assert still[0, 2:, 0].sub(0.35).abs().max() < 0.25
    assert free[0, 2:, 0].sub(0.35).abs().max() > 0.5  # without it the trend overshoots


def test_catmull_rom_basis_is_the_catmull_rom_spline_as_weights_of_its_keys():
    gen = torch.Generator().manual_seed(3)
    key_times = torch.tensor([0.0, 0.15, 0.4, 0.55, 1.0], dtype=torch.float64)
    keys = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    tangents = hermite.catmull_rom_tangents(key_times, keys)
    for t in (-0.2, 0.0, 0.1, 0.15, 0.47, 0.9, 1.0, 1.3):
        b = hermite.catmull_rom_basis(key_times.numpy(), t)
        want = hermite.hermite_eval(key_times, keys, tangents, torch.tensor([t], dtype=torch.float64))[0]
        np.testing.assert_allclose(b @ keys.numpy(), want.numpy(), atol=1e-12)
    assert hermite.catmull_rom_basis(np.array([0.3]), 0.7).tolist() == [1.0]
