"""Rasteriser on CUDA (skipped without a GPU): reference is device-agnostic, gsplat agrees.

Run on the device machine with ``pytest -s`` to see the measured differences.
"""

from __future__ import annotations

import importlib.util

import pytest
import torch

from engine.bench.raster import make_scene
from engine.raster import render

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _loss_and_grads(backend, scene, device, dtype):
    leaves = {k: scene[k].to(device, dtype).clone().requires_grad_(True)
              for k in ("means", "quats", "scales", "opacities", "colors", "background")}
    out = render(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], colors=leaves["colors"],
                 w2c=scene["w2c"].to(device, dtype), K=scene["K"].to(device, dtype), width=scene["width"],
                 height=scene["height"], background=leaves["background"], backend=backend)
    g = torch.Generator().manual_seed(0)
    h, w = scene["height"], scene["width"]
    wr, wa, wd = (torch.randn(h, w, c, generator=g).to(device, dtype) for c in (3, 1, 1))
    ((out.rgb * wr).sum() + (out.alpha * wa).sum() + 0.2 * (out.depth * wd).sum()).backward()
    grads = {k: v.grad.detach().double().cpu() for k, v in leaves.items()}
    grads["means2d"] = out.grad2d().detach().double().cpu()
    return out, grads


def _scene(n=400, res=64):
    s = make_scene(n, res, seed=1)
    s["opacities"] = s["opacities"].clamp(max=0.98)  # gsplat clamps alpha at 0.999, we at 0.99
    s["scales"] = s["scales"] * 4.0
    s["background"] = torch.tensor([0.1, 0.4, 0.7])
    return s


def _report(tag, a, b, ga, gb):
    errs = {k: (getattr(a, k).double().cpu() - getattr(b, k).double().cpu()).abs().max().item()
            for k in ("rgb", "alpha", "depth")}
    rel = {k: ((ga[k] - gb[k]).norm() / gb[k].norm().clamp_min(1e-12)).item() for k in gb}
    print(f"\n[{tag}] forward max abs err: {errs}\n[{tag}] gradient rel err: {rel}")
    return errs, rel


def test_reference_cuda_matches_cpu():
    s = _scene()
    a, ga = _loss_and_grads("reference", s, "cuda", torch.float64)
    b, gb = _loss_and_grads("reference", s, "cpu", torch.float64)
    errs, rel = _report("reference cuda vs cpu", a, b, ga, gb)
    assert max(errs.values()) <= 1e-9 and max(rel.values()) <= 1e-9


@pytest.mark.skipif(importlib.util.find_spec("gsplat") is None, reason="gsplat not installed")
def test_gsplat_matches_reference():
    s = _scene()
    a, ga = _loss_and_grads("auto", s, "cuda", torch.float32)
    assert a.backend == "gsplat"
    b, gb = _loss_and_grads("reference", s, "cuda", torch.float64)
    errs, rel = _report("gsplat vs reference", a, b, ga, gb)
    assert torch.equal(a.visible.cpu(), b.visible.cpu()) or (a.visible.cpu() != b.visible.cpu()).sum() <= 2
    assert max(errs.values()) <= 1e-3, errs
    assert max(rel.values()) <= 1e-2, rel


@pytest.mark.skipif(importlib.util.find_spec("gsplat") is None, reason="gsplat not installed")
def test_gsplat_extra_channel_matches_reference():
    """``extra=`` rides as a fourth colour channel through gsplat (background 0, detached)."""
    s = _scene()
    extra = torch.rand(len(s["means"]), generator=torch.Generator().manual_seed(2))
    outs, grads = {}, {}
    for backend, dtype in (("gsplat", torch.float32), ("reference", torch.float64)):
        leaves = {k: s[k].to("cuda", dtype).clone().requires_grad_(True)
                  for k in ("means", "quats", "scales", "opacities", "colors", "background")}
        out = render(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], colors=leaves["colors"],
                     w2c=s["w2c"].to("cuda", dtype), K=s["K"].to("cuda", dtype), width=s["width"],
                     height=s["height"], background=leaves["background"], extra=extra.to("cuda", dtype),
                     backend=backend)
        we = torch.randn(s["height"], s["width"], 1, generator=torch.Generator().manual_seed(3)).to("cuda", dtype)
        ((out.extra * we).sum() + out.rgb.sum()).backward()
        outs[backend] = out
        grads[backend] = {k: v.grad.detach().double().cpu() for k, v in leaves.items() if k != "colors"}
    a, b = outs["gsplat"], outs["reference"]
    assert a.extra.shape == (s["height"], s["width"], 1) and a.rgb.shape[-1] == 3 and a.depth.shape[-1] == 1
    for name in ("extra", "rgb", "depth"):
        err = (getattr(a, name).double().cpu() - getattr(b, name).double().cpu()).abs().max().item()
        assert err <= 1e-3, (name, err)
    for k, g in grads["reference"].items():
        rel = ((grads["gsplat"][k] - g).norm() / g.norm().clamp_min(1e-12)).item()
        assert rel <= 1e-2, (k, rel)
