"""The fused Numba deformation (engine/train/fused.py) against the torch reference:
values and gradients (means, quats, spline keys), antipodal node quaternions included."""

import torch

import engine.train.model as M
from engine.train.split import resting_nodes


def _scene(seed=0, g=2000, n=48, k=6):
    torch.manual_seed(seed)
    means = torch.randn(g, 3)
    cent = torch.randn(n, 3)
    kt = torch.linspace(0, 1, k)
    pk = cent[:, None] + 0.3 * torch.randn(n, k, 3)
    rk = torch.randn(n, k, 4)  # random signs: exercises the hemisphere alignment
    m = M.DynamicScene(means, torch.rand(g, 3), torch.full((g, 3), 0.01), torch.full((g,), 0.3), cent,
                       torch.full((n,), 0.8), kt, pk, rk)
    m.rebind()
    with torch.no_grad():
        m.quats.copy_(torch.randn(g, 4))
    return m


def _run(m, fused, t=0.37):
    old = M.FUSED_DEFORM
    M.FUSED_DEFORM = fused
    try:
        m.zero_grad(set_to_none=True)
        x, q = m.deform(t)
        gen = torch.Generator().manual_seed(1)
        gx, gq = torch.randn(x.shape, generator=gen), torch.randn(q.shape, generator=gen)
        ((x * gx).sum() + (q * gq).sum()).backward()
        return [x.detach(), q.detach(), m.means.grad.clone(), m.quats.grad.clone(), m.pos_keys.grad.clone(),
                m.rot_keys.grad.clone()]
    finally:
        M.FUSED_DEFORM = old


def test_fused_deform_matches_reference():
    m = _scene()
    ref, fus = _run(m, False), _run(m, True)
    for name, r, f in zip(["means_t", "quats_t", "g_means", "g_quats", "g_pos_keys", "g_rot_keys"], ref, fus):
        tol = 1e-5 * (1.0 + float(r.abs().max()))
        assert torch.allclose(r, f, atol=tol, rtol=1e-4), (name, float((r - f).abs().max()))


def test_fused_deform_is_deterministic():
    m = _scene(seed=3)
    a, b = _run(m, True), _run(m, True)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


def test_fused_deform_does_not_depend_on_the_thread_count():
    """Row blocks are dealt to one strand per thread (engine/train/fused.py, ROW_BLOCK): the
    values and gradients are the same whichever thread does a row, resting rows included
    (2000 rows: the last block is partial)."""
    import numba

    m = _scene(seed=4)
    with torch.no_grad():
        static = torch.arange(m.num_nodes) % 2 == 0
        m.node_dyn.copy_(~static)
        m.pos_keys[static] = m.node_centers[static][:, None]
        m.rot_keys[static] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    m.rebind()
    n = torch.get_num_threads()
    runs = []
    try:
        for threads in (1, min(3, numba.config.NUMBA_NUM_THREADS)):
            torch.set_num_threads(threads)
            runs.append(_run(m, True))
    finally:
        torch.set_num_threads(n)
    for x, y in zip(*runs):
        assert torch.equal(x, y)


def test_fused_deform_points_matches_reference():
    m = _scene(seed=5)
    pts = torch.randn(300, 3, requires_grad=True)
    idx, w = m.bind_idx[:300], m.bind_w[:300]
    outs = []
    for fused in (False, True):
        old = M.FUSED_DEFORM
        M.FUSED_DEFORM = fused
        try:
            m.zero_grad(set_to_none=True)
            pts.grad = None
            x = m.deform_points(pts, idx, w, 0.61)
            (x * torch.linspace(-1, 1, x.numel()).view_as(x)).sum().backward()
            outs.append((x.detach(), pts.grad.clone(), m.pos_keys.grad.clone(), m.rot_keys.grad.clone()))
        finally:
            M.FUSED_DEFORM = old
    for r, f in zip(*outs):
        assert torch.allclose(r, f, atol=1e-5 * (1 + float(r.abs().max())), rtol=1e-4)


def test_fused_knn_matches_geometry_knn():
    """The binding refresh's Numba K-NN ranks nodes like engine.geometry.binding.knn_nodes."""
    from engine.geometry.binding import knn_nodes
    from engine.train.fused import fused_knn

    torch.manual_seed(3)
    pts = torch.randn(5000, 3) * 2 + 40.0  # far from the origin: the centred ranking matters
    nodes = torch.randn(300, 3) * 2 + 40.0
    ref, _ = knn_nodes(pts, nodes, 4)
    assert torch.equal(fused_knn(pts, nodes, 4), ref)
    assert torch.equal(fused_knn(pts, nodes, 4), fused_knn(pts, nodes, 4))


def test_static_gaussians_at_rest_pass_through_and_the_rest_match_the_reference():
    """With the split, Gaussians bound only to static nodes whose transform is the identity
    (rest keys) are not blended: their centres come back unchanged, their rotations
    normalised, and the moving Gaussians get the reference's values and gradients."""
    m = _scene(seed=5)
    n = m.num_nodes
    static = torch.arange(n) % 3 == 0
    with torch.no_grad():
        m.node_dyn.copy_(~static)
        m.pos_keys[static] = m.node_centers[static][:, None]  # rest keys
        m.rot_keys[static] = torch.tensor([2.0, 0.0, 0.0, 0.0])  # identity, not unit
        m.gauss_dyn.copy_(torch.arange(m.num_gaussians) % 4 != 0)
    m.rebind()
    rest = ~m.node_dyn[m.bind_idx].any(1)
    assert 100 < int(rest.sum()) < m.num_gaussians - 100
    dq = m.node_dq(0.37)
    assert bool(resting_nodes(m, dq)[static].all()) and not bool(resting_nodes(m, dq)[~static].any())
    ref, fus = _run(m, False), _run(m, True)
    assert torch.equal(fus[0][rest], m.means.detach()[rest])
    q = m.quats.detach()[rest]
    assert torch.allclose(fus[1][rest], q / q.norm(dim=1, keepdim=True), atol=1e-6)
    for name, r, f in zip(["means_t", "quats_t", "g_means", "g_quats"], ref, fus):
        tol = 1e-5 * (1.0 + float(r.abs().max()))
        assert torch.allclose(r, f, atol=tol, rtol=1e-4), (name, float((r - f).abs().max()))
    # the moving nodes' key gradients are the reference's; the static ones get none
    dyn = ~static
    for r, f in zip(ref[4:], fus[4:]):
        assert torch.allclose(r[dyn], f[dyn], atol=1e-5 * (1.0 + float(r.abs().max())), rtol=1e-4)
        assert float(f[static].abs().sum()) == 0.0


def test_a_static_node_moved_on_purpose_still_deforms_its_gaussians():
    """A static node whose keys were edited (not at rest) is not taken as the identity."""
    m = _scene(seed=6)
    static = torch.arange(m.num_nodes) % 2 == 0
    with torch.no_grad():
        m.node_dyn.copy_(~static)
        m.pos_keys[static] = m.node_centers[static][:, None] + torch.tensor([0.0, 0.2, 0.0])
        m.rot_keys[static] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    m.rebind()
    assert not bool(resting_nodes(m, m.node_dq(0.5)).any())
    ref, fus = _run(m, False, t=0.5), _run(m, True, t=0.5)
    assert torch.allclose(ref[0], fus[0], atol=1e-5)
