"""Scoring a run on its own frames: the renders and figures the trainer reports.

:func:`render_frame` renders one frame of the :class:`~engine.train.data.TrainingData` at its
time (only the Gaussians that time can show, :func:`~engine.train.lifespan.shown_gaussians`),
:func:`evaluate_frames` scores frames against the images (whole-image PSNR / SSIM, and masked
PSNR where a dynamic prior exists), :func:`spread_sample` picks the training frames the
training-view score uses and :func:`quality_lines` words the result beside the still plate.
The ``engine eval`` command scores a saved bundle the same way (``engine/commands/eval.py``).
"""

from __future__ import annotations

import numpy as np
import torch

from . import losses as L
from .lifespan import shown_gaussians
from .render import render_scene


@torch.no_grad()
def render_frame(model, data, f: int, t: float | None = None, backend: str = "auto", cull: bool = True):
    """Render frame ``f`` of ``data`` with ``model`` at engine time ``t`` (default: the
    frame's own); a :class:`~engine.raster.RenderOutput` (with ``cull`` its per-Gaussian
    outputs are the shown rows only)."""
    d, m = data, model
    t = float(d.times[f]) if t is None else t
    shown = shown_gaussians(m, t) if cull else None
    means_t, quats_t = m.deform(t, index=shown)
    return render_scene(m, means_t, quats_t, d.K[f], d.w2c[f], d.width, d.height, backend=backend, time=t,
                        index=shown)


@torch.no_grad()
def evaluate_frames(model, data, idx: torch.Tensor, backend: str = "auto", cull: bool = True) -> dict:
    """``{"frames", "psnr", "ssim"[, "masked_psnr"]}`` over frames ``idx [F]`` (means over the
    frames; masked PSNR inside the dynamic prior > 0.5 on frames with more than 16 such
    pixels); ``{"frames": 0}`` when ``idx`` is empty."""
    d = data
    if len(idx) == 0:
        return {"frames": 0}
    ps, ss, mps = [], [], []
    for f in idx.tolist():
        pred = render_frame(model, d, f, backend=backend, cull=cull).rgb.clamp(0, 1)
        ps.append(float(L.psnr(pred, d.images[f])))
        ss.append(float(L.ssim(pred, d.images[f])))
        if d.fg is not None and float(d.fg[f].sum()) > 16:
            mps.append(float(L.psnr(pred, d.images[f], (d.fg[f] > 0.5).to(pred.dtype).unsqueeze(-1))))
    res = {"frames": len(ps), "psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}
    if mps:
        res["masked_psnr"] = float(np.mean(mps))
    return res


def spread_sample(idx: torch.Tensor, at_most: int = 30) -> torch.Tensor:
    """Up to ``at_most`` of the frames ``idx [F]`` spread evenly over them (all when fewer)."""
    if len(idx) <= at_most:
        return idx
    return idx[torch.linspace(0, len(idx) - 1, at_most).round().long()]


def quality_lines(metrics: dict) -> list[str]:
    """One line per scored split of a run's ``metrics`` (``eval_train`` / ``eval``): whole-image
    PSNR beside the still plate's (``metrics["still_plate"]``) when it is known."""
    plate = metrics.get("still_plate") or {}
    lines = []
    for key, split, name in (("eval_train", "train", "training frames"), ("eval", "val", "held-out frames")):
        ev = metrics.get(key) or {}
        if not ev.get("frames"):
            continue
        line = f"{name}: PSNR {ev['psnr']:.2f} dB over {ev['frames']}"
        if plate.get(split) is not None:
            line += f" (still plate {plate[split]:.2f} dB, {ev['psnr'] - plate[split]:+.2f})"
        lines.append(line)
    return lines
