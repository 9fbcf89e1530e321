"""The ``compile`` stage: load (or, on a first run, compile) the Numba kernels up front.

The CPU path runs Numba kernels (the tile rasteriser in :mod:`engine.raster.cpu_numba`
and the fused training kernels in ``engine/train/fused*.py``). They are compiled lazily
on their first call and cached on disk (``cache=True``; ``NUMBA_CACHE_DIR``): a first
run spends about a minute compiling inside its first render, a later run loads them
from the cache in a second or two. Without this stage that minute showed as the stage
before it, finished, with no ETA.

:func:`warm_kernels` calls every kernel group once on a tiny synthetic scene (forward
and backward), with the argument types training uses (the public wrappers convert their
inputs to fixed dtypes), and reports progress ``compile`` after each group, in steps
weighted by a group's share of a cold compile (:data:`GROUPS`). The ETA is the
Reporter's, from the measured rate. A log line says how
long it took and whether anything was compiled (Numba's ``numba:compile`` event fires
only for a real compilation, not for a cache load).
"""

from __future__ import annotations

import time

import torch

STAGE = "compile"


def _raster(with_extra: bool) -> None:
    from ..raster import render

    g = torch.Generator().manual_seed(0)
    n = 24
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([1.0, 1.0, 0.0]) + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.full((n, 3), 0.08)
    opac = torch.full((n,), 0.7)
    colors = torch.rand(n, 3, generator=g)
    for t in (means, quats, scales, opac, colors):
        t.requires_grad_(True)
    K = torch.tensor([[20.0, 0.0, 12.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    extra = torch.rand(n, generator=g) if with_extra else None  # the extra-channel kernels, or the plain ones
    out = render(means, quats, scales, opac, colors=colors, w2c=w2c, K=K, width=24, height=20,
                 background=torch.zeros(3), extra=extra, backend="cpu")
    loss = out.rgb.sum() + out.alpha.sum() + out.depth.sum()
    if out.extra is not None:
        loss = loss + out.extra.sum()
    loss.backward()


def _sh() -> None:
    from .fused_sh import fused_sh_colors

    g = torch.Generator().manual_seed(1)
    n = 16
    means = torch.randn(n, 3, generator=g).requires_grad_(True)
    dc = torch.rand(n, 1, 3, generator=g).requires_grad_(True)
    rest = (0.1 * torch.randn(n, 3, 3, generator=g)).requires_grad_(True)
    fused_sh_colors(means, dc, rest, 1, torch.eye(4)).sum().backward()


def _ssim() -> None:
    from .fused_ssim import fused_ssim

    g = torch.Generator().manual_seed(2)
    pred = torch.rand(16, 16, 3, generator=g).requires_grad_(True)
    fused_ssim(pred, torch.rand(16, 16, 3, generator=g)).backward()


def _image() -> None:
    from .fused_image import fused_depth_term, fused_l1_terms
    from .fused_points import fused_on_mask, fused_track

    g = torch.Generator().manual_seed(5)
    pred = torch.rand(12, 10, 3, generator=g).requires_grad_(True)
    target = torch.rand(12, 10, 3, generator=g)
    weight = 1.0 + torch.rand(12, 10, 1, generator=g)
    for w, pools in ((weight, (4, 8)), (None, ())):  # with and without the coarse term
        l1, coarse, _mse = fused_l1_terms(pred, target, w, pools)
        (l1 + coarse).backward()
    depth_sum = torch.rand(12, 10, generator=g).requires_grad_(True)
    fused_depth_term(depth_sum, torch.ones(12, 10), torch.rand(12, 10, generator=g) + 0.5).backward()
    points = (torch.rand(8, 3, generator=g) + torch.tensor([0.0, 0.0, 2.0])).requires_grad_(True)
    K = torch.tensor([[10.0, 0.0, 5.0], [0.0, 10.0, 6.0], [0.0, 0.0, 1.0]])
    fused_on_mask(points, K, torch.eye(4), torch.rand(12, 10, generator=g), 0.1).backward()
    fused_track(points, K, torch.eye(4), torch.rand(8, 2, generator=g), 0.1).backward()


def _nodes() -> None:
    from .fused_nodes import fused_node_state

    g = torch.Generator().manual_seed(6)
    n, k = 6, 5
    pos = torch.randn(n, k, 3, generator=g).requires_grad_(True)
    rot = torch.randn(n, k, 4, generator=g).requires_grad_(True)
    p, r, dq = fused_node_state(pos, rot, 1, torch.tensor([0.1, 0.6, 0.4, -0.1]), torch.randn(n, 3, generator=g))
    (p.sum() + r.sum() + dq.sum()).backward()


def _deform() -> None:
    from .fused import fused_deform, fused_knn

    g = torch.Generator().manual_seed(3)
    nodes, gauss, k = 8, 32, 4
    dq = torch.zeros(nodes, 8)
    dq[:, 0] = 1.0
    dq.requires_grad_(True)
    pts = torch.randn(gauss, 3, generator=g)
    idx = fused_knn(pts, torch.randn(nodes, 3, generator=g), k)
    w = torch.full((gauss, k), 1.0 / k)
    means = pts.clone().requires_grad_(True)
    quats = torch.nn.functional.normalize(torch.randn(gauss, 4, generator=g), dim=-1).requires_grad_(True)
    rest = torch.zeros(nodes, dtype=torch.bool)
    rest[:3] = True
    for normalize, node_rest in ((False, None), (True, None), (True, rest)):
        x, q = fused_deform(dq, idx, w, means, quats, normalize=normalize, node_rest=node_rest)
        (x.sum() + q.sum()).backward()


def _reg() -> None:
    from .fused_reg import fused_arap, fused_key_terms

    g = torch.Generator().manual_seed(4)
    n, k = 8, 5
    p0, p1 = torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g).requires_grad_(True)
    q0 = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    q1 = q0.clone().requires_grad_(True)
    graph = torch.randint(0, n, (n, 3), generator=g)
    fused_arap(p0, q0, p1, q1, graph).backward()
    pos = torch.randn(n, k, 3, generator=g).requires_grad_(True)
    rot = torch.nn.functional.normalize(torch.randn(n, k, 4, generator=g), dim=-1).requires_grad_(True)
    times = torch.linspace(0, 1, k)
    s, arm = torch.rand(n, generator=g), torch.rand(n, generator=g)
    for ref in (None, (pos.detach().clone(), rot.detach().clone())):
        st, vel, acc = fused_key_terms(pos, rot, times, s, arm, 1.0, *(ref or ()))
        (st + vel + acc).backward()


#: ``(name, call, weight)``: the progress steps of each group are its share of a cold
#: compile, in seconds (measured on a shared 2-core CPU at 97 s in all), so that the
#: rate, and so the ETA, is about even through the stage.
GROUPS = (("rasteriser", lambda: _raster(False), 43), ("rasteriser extra channel", lambda: _raster(True), 19),
          ("SH colours", _sh, 3), ("SSIM", _ssim, 13), ("image terms", _image, 15),
          ("node splines", _nodes, 4), ("deformation", _deform, 19), ("regularisers", _reg, 9))


def kernel_groups(device="cpu", backend: str = "auto") -> tuple:
    """The :data:`GROUPS` a run on ``device`` with rasteriser ``backend`` uses: none off the
    CPU or without Numba; the rasteriser only when ``backend`` resolves to ``cpu``."""
    from ..raster.api import numba_available, select_backend

    device = torch.device(device)
    if device.type != "cpu" or not numba_available():
        return ()
    raster = select_backend(backend, device) == "cpu"
    return tuple(g for g in GROUPS if raster or not g[0].startswith("rasteriser"))


def warm_kernels(reporter, device="cpu", backend: str = "auto") -> dict | None:
    """Run the ``compile`` stage (see the module docstring); ``None`` when the run uses no
    Numba kernel. Returns ``{"seconds", "compiled"}``: the stage's wall time and the number
    of Numba compilations it triggered (0: everything came from the cache)."""
    groups = kernel_groups(device, backend)
    if not groups:
        return None
    from numba.core import event

    total = sum(weight for _name, _call, weight in groups)
    t0 = time.monotonic()
    done = 0
    reporter.progress(STAGE, done, total)
    with event.install_recorder("numba:compile") as rec, torch.enable_grad():
        for _name, call, weight in groups:
            call()
            done += weight
            reporter.progress(STAGE, done, total)
    compiled = sum(1 for _t, ev in rec.buffer if ev.kind == "numba:compile" and ev.is_start)
    seconds = round(time.monotonic() - t0, 2)
    how = f"compiled ({compiled} compilations; cached for the next run)" if compiled else "loaded from the cache"
    reporter.log(f"engine kernels {how} in {seconds:.1f} s")
    return {"seconds": seconds, "compiled": compiled}
