"""Rasteriser: cpu (Numba) backend against the dense float64 reference, plus API checks."""

from __future__ import annotations

import pytest
import torch

from engine.raster import api, reference, render, scales_from_log, select_backend
from engine.raster.sh import num_sh_bases

W, H = 48, 40


def _camera(dtype=torch.float64):
    # A rotated, translated camera so that the world->camera transform is exercised.
    ang = torch.tensor(0.3, dtype=torch.float64)
    c, s = torch.cos(ang), torch.sin(ang)
    R = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = torch.tensor([0.2, -0.1, 0.5])
    K = torch.tensor([[45.0, 0, W / 2 + 1.3], [0, 47.0, H / 2 - 0.7], [0, 0, 1]], dtype=torch.float64)
    return w2c.to(dtype), K.to(dtype)


def _scene(n=160, seed=0, sh_degree=None):
    """Random scene in camera space mapped to world, with the awkward cases mixed in."""
    g = torch.Generator().manual_seed(seed)
    z = 1.0 + 5.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * 1.4 * z  # ~40 % partly or fully off-screen
    y = (torch.rand(n, generator=g) - 0.5) * 1.4 * z
    pc = torch.stack([x, y, z], -1).double()
    log_s = torch.randn(n, 3, generator=g).double() * 0.5 - 2.6
    pc[:6, 2] = -pc[:6, 2]  # behind the camera
    pc[6, 2] = 0.005  # between camera and near plane
    log_s[10:16, 0] = -9.0  # very thin (needles / discs)
    log_s[16:19] = log_s[16:19] + 2.5  # very large, cover much of the image
    log_s[19, :] = 1.0  # huge and close: its Jacobian clamps x/z, y/z
    pc[19] = torch.tensor([0.3, 0.2, 1.2], dtype=torch.float64)
    w2c, K = _camera()
    R, t = w2c[:3, :3], w2c[:3, 3]
    means = (pc - t) @ R  # world = R^T (p - t)
    quats = torch.randn(n, 4, generator=g).double()
    opac = (0.02 + 0.96 * torch.rand(n, generator=g)).double()
    opac[20] = 0.999  # exercises the 0.99 alpha clamp
    p = dict(means=means, quats=quats, scales=torch.exp(log_s), opacities=opac)
    if sh_degree is None:
        p["colors"] = torch.rand(n, 3, generator=g).double()
    else:
        p["sh"] = 0.3 * torch.randn(n, num_sh_bases(sh_degree), 3, generator=g).double()
    p["background"] = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)
    return p


def _run(backend, scene, dtype, sh_degree=None, seed=1, extra=None):
    w2c, K = _camera(dtype)
    leaves = {k: v.clone().to(dtype).requires_grad_(True) for k, v in scene.items()}
    out = render(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                 colors=leaves.get("colors"), sh=leaves.get("sh"), sh_degree=sh_degree,
                 w2c=w2c, K=K, width=W, height=H, background=leaves["background"], backend=backend,
                 extra=None if extra is None else extra.to(dtype))
    g = torch.Generator().manual_seed(seed)
    wr, wa, wd, we = (torch.randn(H, W, c, generator=g).to(dtype) for c in (3, 1, 1, 1))
    loss = (out.rgb * wr).sum() + (out.alpha * wa).sum() + 0.2 * (out.depth * wd).sum()
    if extra is not None:
        loss = loss + 0.7 * (out.extra * we).sum()
    loss.backward()
    grads = {k: v.grad for k, v in leaves.items()}
    grads["means2d"] = out.grad2d()
    return out, grads


def _rel(a, b):
    a, b = a.double(), b.double()
    return ((a - b).norm() / b.norm().clamp_min(1e-12)).item()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cpu_matches_reference_colors(seed):
    scene = _scene(seed=seed)
    ref, gref = _run("reference", scene, torch.float64)
    cpu, gcpu = _run("cpu", scene, torch.float32)
    assert cpu.backend == "cpu" and ref.backend == "reference"
    for name in ("rgb", "alpha", "depth"):
        err = (getattr(cpu, name).double() - getattr(ref, name)).abs().max().item()
        assert err <= 1e-4, (name, err)
    assert torch.equal(cpu.radii, ref.radii)
    assert torch.equal(cpu.visible, ref.visible)
    assert not cpu.visible[:7].any()  # behind the camera / before the near plane
    for name, g in gref.items():
        assert g is not None and g.norm() > 0, name
        assert _rel(gcpu[name], g) <= 1e-3, (name, _rel(gcpu[name], g))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_cpu_matches_reference_sh(degree):
    scene = _scene(n=120, seed=10 + degree, sh_degree=degree)
    ref, gref = _run("reference", scene, torch.float64, sh_degree=degree)
    cpu, gcpu = _run("cpu", scene, torch.float32, sh_degree=degree)
    for name in ("rgb", "alpha", "depth"):
        assert (getattr(cpu, name).double() - getattr(ref, name)).abs().max().item() <= 1e-4, name
    for name, g in gref.items():
        assert _rel(gcpu[name], g) <= 1e-3, (name, _rel(gcpu[name], g))


def test_cpu_binning_chunks_match_reference(monkeypatch):
    """Many small binning chunks (uneven sizes) and Gaussians spanning several tiles: the
    per-chunk counting sort, the per-tile depth order and the Gaussian-major gradient
    slots must give the reference's result."""
    from engine.raster import cpu_numba

    monkeypatch.setattr(cpu_numba, "BIN_CHUNK", 37)
    scene = _scene(n=200, seed=7)
    scene["scales"] = scene["scales"] * 1.5  # more multi-tile footprints
    ref, gref = _run("reference", scene, torch.float64)
    cpu, gcpu = _run("cpu", scene, torch.float32)
    for name in ("rgb", "alpha", "depth"):
        assert (getattr(cpu, name).double() - getattr(ref, name)).abs().max().item() <= 1e-4, name
    for name, g in gref.items():
        assert _rel(gcpu[name], g) <= 1e-3, (name, _rel(gcpu[name], g))


def test_reference_row_bands_match_one_band(monkeypatch):
    """The reference composites bands of rows to bound its memory (a full frame on a GPU
    without gsplat once took 64 GB): bands of a few rows give the one-band image and gradients."""
    scene = _scene(n=120, seed=3)
    one, gone = _run("reference", scene, torch.float64)
    calls = []
    composite = reference._composite_rows
    monkeypatch.setattr(reference, "_composite_rows", lambda *a: calls.append(a[5:7]) or composite(*a))
    for budget in (120 * W, 120 * W * 5 - 1):  # >= 1 row per band; several rows, uneven last band
        monkeypatch.setattr(reference, "DENSE_BUDGET", budget)
        calls.clear()
        banded, gband = _run("reference", scene, torch.float64)
        assert len(calls) > 2 and calls[-1][1] == H, calls
        for name in ("rgb", "alpha", "depth"):
            assert torch.allclose(getattr(banded, name), getattr(one, name), atol=1e-12), name
        for name, g in gone.items():
            assert torch.allclose(gband[name], g, atol=1e-10), name


def test_small_gaussians_on_tile_borders_per_gaussian():
    """Footprints of a few pixels straddling the 16-px tile borders (the backward's narrow
    path, whose per-lane sums run down the rows of each tile's part of a Gaussian): every
    Gaussian's own gradient must match the reference, not only the gradient norms."""
    g = torch.Generator().manual_seed(11)
    n = 150
    w2c, K = _camera()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = 16.0 * torch.randint(1, 3, (n,), generator=g) + 4.0 * (torch.rand(n, generator=g) - 0.5)
    v = 16.0 * torch.randint(1, 3, (n,), generator=g) + 4.0 * (torch.rand(n, generator=g) - 0.5)
    z = 2.0 + 2.0 * torch.rand(n, generator=g)
    pc = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1).double()
    R, t = w2c[:3, :3], w2c[:3, 3]
    sigma_px = 0.5 + 1.2 * torch.rand(n, 3, generator=g)
    scene = dict(means=(pc - t) @ R, quats=torch.randn(n, 4, generator=g).double(),
                 scales=(sigma_px * (z / fx)[:, None]).double(),
                 opacities=(0.1 + 0.85 * torch.rand(n, generator=g)).double(),
                 colors=torch.rand(n, 3, generator=g).double(),
                 background=torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64))
    ref, gref = _run("reference", scene, torch.float64)
    cpu, gcpu = _run("cpu", scene, torch.float32)
    for name in ("rgb", "alpha", "depth"):
        assert (getattr(cpu, name).double() - getattr(ref, name)).abs().max().item() <= 1e-4, name
    for name in ("means", "quats", "scales", "opacities", "colors", "means2d"):
        a, b = gcpu[name].double().reshape(n, -1), gref[name].reshape(n, -1)
        scale = b.abs().max()
        assert scale > 0, name
        err = ((a - b).abs().max(1).values / (b.abs().max(1).values + 1e-3 * scale)).max().item()
        assert err <= 1e-3, (name, err)


def test_cpu_renders_in_flight_keep_their_buffers():
    """Scratch buffers are pooled across calls: two renders whose backward runs later (the
    first render's tile records are still held by its autograd context when the second
    one bins) must each get the gradient of a render on its own."""
    w2c, K = _camera(torch.float32)
    scenes = [_scene(n=120, seed=s) for s in (21, 22)]
    kw = dict(w2c=w2c, K=K, width=W, height=H, backend="cpu")

    def leaves(sc):
        return {k: v.clone().float().requires_grad_(True) for k, v in sc.items()}

    def loss(out):
        return (out.rgb * out.rgb).sum() + out.alpha.sum() + 0.2 * out.depth.sum()

    alone = []
    for sc in scenes:
        lv = leaves(sc)
        loss(render(lv["means"], lv["quats"], lv["scales"], lv["opacities"], colors=lv["colors"],
                    background=lv["background"], **kw)).backward()
        alone.append(lv)
    both = [leaves(sc) for sc in scenes]
    outs = [render(lv["means"], lv["quats"], lv["scales"], lv["opacities"], colors=lv["colors"],
                   background=lv["background"], **kw) for lv in both]
    (loss(outs[0]) + loss(outs[1])).backward()
    for a, b in zip(alone, both):
        for k in a:
            assert torch.equal(a[k].grad, b[k].grad), k


def test_tile_strands_cover_every_tile_once_and_balance_the_work():
    """The tile kernels run one strand of tiles per thread: every tile in exactly one strand,
    and (longest-processing-time first) no strand's work above the lightest one's by more
    than the heaviest single tile."""
    import numpy as np

    from engine.raster import cpu_numba as K_

    rng = np.random.default_rng(0)
    counts = rng.integers(0, 40, 180)
    counts[50:60] = rng.integers(500, 1500, 10)  # a dense region: one block of heavy tiles
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    work = counts + K_.TILE_FIXED_WORK
    for nstrands in (1, 2, 3, 8):
        order, starts = K_.tile_strands(offsets, nstrands)
        assert starts[0] == 0 and starts[-1] == 180 and np.all(np.diff(starts) >= 0)
        assert np.array_equal(np.sort(order), np.arange(180))
        loads = np.add.reduceat(work[order], starts[:-1]) if nstrands > 1 else np.array([work.sum()])
        assert loads.sum() == work.sum()
        assert loads.max() - loads.min() <= work.max(), (nstrands, loads)
    # contiguous halves (a static split of the tile range) would leave one thread with the
    # whole dense block; the strands split it
    order, starts = K_.tile_strands(offsets, 2)
    halves = work[:90].sum(), work[90:].sum()
    loads = work[order[:starts[1]]].sum(), work[order[starts[1]:]].sum()
    assert max(loads) < 0.55 * work.sum() < max(halves)


def test_instance_bounds_split_the_gaussians_by_work():
    """sum_instances' strands: contiguous ranges covering every Gaussian once, each with about
    the same instance rows (+1 per Gaussian) however the rows are spread over the Gaussians."""
    import numpy as np

    from engine.raster import cpu_numba as K_

    rng = np.random.default_rng(1)
    ntile = rng.integers(0, 3, 5000)
    ntile[3000:3500] = rng.integers(20, 60, 500)  # a run of large Gaussians
    gstart = np.concatenate([[0], np.cumsum(ntile)]).astype(np.int64)
    work = ntile + 1
    for nstrands in (1, 2, 3, 7):
        bounds = K_.instance_bounds(gstart, nstrands)
        assert bounds[0] == 0 and bounds[-1] == 5000 and np.all(np.diff(bounds) >= 0)
        loads = np.array([work[bounds[s]:bounds[s + 1]].sum() for s in range(nstrands)])
        assert loads.max() - loads.min() <= 2 * work.max(), (nstrands, loads)
    # equal Gaussian counts would not be
    halves = work[:2500].sum(), work[2500:].sum()
    assert abs(halves[0] - halves[1]) > 4 * work.max()
    assert K_.instance_bounds(np.zeros(1, np.int64), 2).tolist() == [0, 0, 0]  # no Gaussians


def test_cpu_render_does_not_depend_on_the_thread_count():
    """Tiles go to threads by work (:func:`tile_strands`); which thread renders a tile must
    change nothing, forward or backward."""
    import numba

    scene = _scene(n=400, seed=9)
    n = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, min(3, numba.config.NUMBA_NUM_THREADS)):
            torch.set_num_threads(threads)
            runs.append(_run("cpu", scene, torch.float32))
    finally:
        torch.set_num_threads(n)
    (o1, g1), (o2, g2) = runs
    for a, b in ((o1.rgb, o2.rgb), (o1.alpha, o2.alpha), (o1.depth, o2.depth)):
        assert torch.equal(a, b)
    for k in g1:
        assert torch.equal(g1[k], g2[k]), k


def test_scratch_pool_reuses_only_free_buffers():
    import numpy as np

    from engine.raster import cpu_numba

    a = cpu_numba.pooled("test_pool", 1000, np.float32)
    base_a = id(a.base)
    b = cpu_numba.pooled("test_pool", 1000, np.float32)  # a is alive: another buffer
    assert id(b.base) != base_a
    del a
    c = cpu_numba.pooled("test_pool", 800, np.float32)  # a's buffer is free again
    assert id(c.base) == base_a and c.shape == (800,)
    del b, c
    d = cpu_numba.pooled("test_pool", 10_000, np.float32)  # grows
    assert d.shape == (10_000,)


@pytest.mark.parametrize("seed", [0, 3])
def test_extra_channel_matches_reference_and_a_second_render(seed):
    """``extra`` rides in the colour pass: the cpu kernels' extra variant against the
    reference, and against what it replaces -- a second render with the scalar as colour
    and no background, whose gradient adds to the first's."""
    scene = _scene(seed=seed)
    extra = torch.rand(len(scene["means"]), generator=torch.Generator().manual_seed(seed)).double()
    ref, gref = _run("reference", scene, torch.float64, extra=extra)
    cpu, gcpu = _run("cpu", scene, torch.float32, extra=extra)
    plain, gplain = _run("cpu", scene, torch.float32)
    assert cpu.extra.shape == (H, W, 1) and plain.extra is None and ref.extra.shape == (H, W, 1)
    assert (cpu.extra.double() - ref.extra).abs().max().item() <= 1e-4
    assert cpu.extra.abs().max() > 0.1
    for name in ("rgb", "alpha", "depth"):  # the colour pass is untouched by the extra channel
        assert torch.equal(getattr(cpu, name), getattr(plain, name)), name
    for name, g in gref.items():
        assert _rel(gcpu[name], g) <= 1e-3, (name, _rel(gcpu[name], g))
    # the extra term's gradient is really there: it moves the result away from the plain run
    assert _rel(gcpu["means"], gplain["means"]) > 1e-2

    # a second render of the scalar as a colour (the same weights) gives the same image,
    # and its gradient is the difference between the two runs above
    w2c, K = _camera(torch.float32)
    leaves = {k: scene[k].float().requires_grad_(True) for k in ("means", "quats", "scales", "opacities")}
    second = render(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                    colors=extra.float()[:, None].expand(-1, 3).contiguous(), w2c=w2c, K=K, width=W, height=H,
                    backend="cpu")
    assert torch.allclose(second.rgb[..., :1], cpu.extra, atol=1e-6)
    g = torch.Generator().manual_seed(1)
    we = [torch.randn(H, W, c, generator=g) for c in (3, 1, 1, 1)][3]
    (0.7 * (second.rgb[..., :1] * we).sum()).backward()
    for name in ("means", "quats", "scales", "opacities"):
        diff = gcpu[name] - gplain[name]
        assert _rel(diff, leaves[name].grad) <= 1e-3, (name, _rel(diff, leaves[name].grad))


def test_extra_channel_input_checks():
    scene = _scene(n=30)
    w2c, K = _camera()
    with pytest.raises(ValueError, match="one value per Gaussian"):
        render(scene["means"], scene["quats"], scene["scales"], scene["opacities"], colors=scene["colors"],
               w2c=w2c, K=K, width=W, height=H, extra=torch.zeros(29, dtype=torch.float64))


def test_dense_scene_early_termination():
    """Many opaque Gaussians stacked on one pixel region: the 1e-4 stop rule must agree."""
    scene = _scene(n=300, seed=5)
    scene["opacities"] = torch.full_like(scene["opacities"], 0.95)
    scene["scales"] = scene["scales"] * 3.0
    ref, gref = _run("reference", scene, torch.float64)
    cpu, gcpu = _run("cpu", scene, torch.float32)
    assert (ref.alpha > 0.999).any()  # transmittance reached the stop region
    for name in ("rgb", "alpha", "depth"):
        assert (getattr(cpu, name).double() - getattr(ref, name)).abs().max().item() <= 1e-4, name
    for name, g in gref.items():
        assert _rel(gcpu[name], g) <= 1e-3, (name, _rel(gcpu[name], g))


def test_reference_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    n, w, h = 4, 8, 7
    means = torch.tensor([[0.0, 0.0, 3.0], [0.2, -0.1, 3.5], [-0.3, 0.2, 4.0], [0.1, 0.3, 2.5]], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.full((n, 3), 0.25, dtype=torch.float64) + 0.05 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    opac = torch.tensor([0.6, 0.5, 0.7, 0.4], dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.1, 0.3], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]], dtype=torch.float64)

    def f(m, q, s, o, c, b):
        out = render(m, q, s, o, colors=c, w2c=w2c, K=K, width=w, height=h, background=b, backend="reference")
        return out.rgb, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, tuple(t.requires_grad_(True) for t in (means, quats, scales, opac, colors, bg)),
                                    eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_empty_scene(backend):
    w2c, K = _camera(torch.float32)
    z = lambda *s: torch.zeros(*s, requires_grad=True)  # noqa: E731
    means, quats, scales, opac, colors = z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3)
    bg = torch.tensor([0.25, 0.5, 0.75])
    out = render(means, quats, scales, opac, colors=colors, w2c=w2c, K=K, width=W, height=H, background=bg,
                 backend=backend)
    assert out.rgb.shape == (H, W, 3) and out.alpha.shape == (H, W, 1) and out.depth.shape == (H, W, 1)
    assert torch.allclose(out.rgb, bg.expand(H, W, 3)) and (out.alpha == 0).all() and (out.depth == 0).all()
    out.rgb.sum().backward()
    assert means.grad.shape == (0, 3)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_zero_opacity_scene(backend):
    scene = _scene(n=50, seed=4)
    scene["opacities"] = torch.zeros_like(scene["opacities"])
    out, grads = _run(backend, scene, torch.float32)
    assert (out.alpha == 0).all() and (out.depth == 0).all() and not out.visible.any()
    assert torch.allclose(out.rgb, scene["background"].float().expand(H, W, 3))
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.count_nonzero(grads[name]) == 0, name


def test_backend_selection_and_threads(monkeypatch):
    assert select_backend("auto", torch.device("cpu")) == "cpu"
    assert select_backend("reference", torch.device("cpu")) == "reference"
    with pytest.raises(ValueError):
        select_backend("opengl", torch.device("cpu"))
    expected = "gsplat" if api.gsplat_available() else "reference"
    assert select_backend("auto", torch.device("cuda")) == expected
    # a render (forward and backward) leaves torch's process-wide thread count alone: it is
    # set once where the process starts (engine/runtime.py), never per render (#19)
    calls = []
    monkeypatch.setattr(torch, "set_num_threads", lambda k: calls.append(k))
    n = torch.get_num_threads()
    scene = _scene(n=30, seed=6)
    _run("auto", scene, torch.float32)
    assert calls == [] and torch.get_num_threads() == n


def test_scales_from_log_and_input_checks():
    assert torch.allclose(scales_from_log(torch.zeros(2, 3)), torch.ones(2, 3))
    w2c, K = _camera(torch.float32)
    with pytest.raises(ValueError):
        render(torch.zeros(1, 3), torch.ones(1, 4), torch.ones(1, 3), torch.ones(1), w2c=w2c, K=K,
               width=4, height=4)


def test_reference_projection_matches_pinhole():
    """means2d follows K in continuous pixel coordinates (centre of pixel (0,0) at 0.5)."""
    w2c = torch.eye(4)
    K = torch.tensor([[50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]])
    means = torch.tensor([[0.0, 0.0, 2.0], [0.2, -0.1, 2.0]])
    m2, _, depths, radii, _ = reference.project(means, torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 0.01),
                                                torch.ones(2), w2c, K, 32, 24)
    assert torch.allclose(m2, torch.tensor([[16.0, 12.0], [21.0, 9.5]]))
    assert torch.allclose(depths, torch.tensor([2.0, 2.0])) and (radii > 0).all()
