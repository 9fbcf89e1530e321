"""Shot detail: per-frame Gaussians of the moving things, trusted only near the camera that saw them.

Why: a moving Gaussian shown at every time (the model of a clip with cameras of its own to be
seen from) averages its object over the clip; a pixel of motion error blurs the texture, and
the moving regions of the training views cap near 20-22 dB even with exact motion
(docs/benchmarks.md, *What caps the moving regions*). Gaussians held at their own frame
(``lifespan_anchor``) reach 27 dB there, but from a second camera they need each moving
object's depth to ~2 %, which no weight-free cue gives (5-7 %): seen from elsewhere they land
a pixel or two off and score below the averaged model (*How near the moving objects' depth
must be*).

So after the main training (:class:`~engine.train.trainer.Trainer`) a second stage seeds, on
every training frame, one Gaussian per moving pixel (up to ``TrainConfig.detail_seeds``, fewer
a frame on a clip whose frames would pass ``detail_seed_max`` in all) in
front of the trained model's own surface there, living only around that frame
(``gauss_lifespan``), bound to the nodes like any moving Gaussian, and **view-bound**: its
opacity is multiplied by

    ``exp(-0.5 (sin(a) / angle)^2)``,  ``angle = detail_fade_px / (f * detail_depth_error)``

where ``a`` is the angle at the Gaussian between the ray from its seed camera
(``gauss_view_origin``) and the ray from the camera rendering it, ``f`` the seed camera's focal
length in pixels. ``f * depth_error * sin(a)`` is how many pixels the seed may be off in that
view given the uncertainty of its depth; where that reaches ``detail_fade_px`` it fades out and
the trained model behind it shows. From its own camera (``a = 0``) a seed is fully there. Only
the new rows train in the stage (colour, opacity, scale, rotation; not the position), for
``detail_steps_per_frame`` steps per training frame, on the photometric loss; everything the
main training learned (the nodes, the static and averaged moving Gaussians) stays as it was.

This is the image-based-rendering idea of blending weights that fall with the angle to the
capturing camera (unstructured lumigraph), applied to Gaussians: the shot re-rendered from its
own cameras gets the per-frame detail, a new view the 3D model.
"""

from __future__ import annotations

import math
import time

import torch

from ..errors import Cancelled
from ..geometry.camera import camera_centers, ray_parallax_sin, unproject
from . import losses as L
from .evaluation import render_frame
from .frame_order import epoch_frame
from .init_model import NodeSubset, distinct_pixels, invert_at_time
from .lifespan import shown_gaussians
from .model import SH_C0, inverse_sigmoid
from .param_edit import edit_rows
from .render import render_scene

#: seeds are placed this fraction of the rendered depth in front of the trained surface, so
#: that they composite over the averaged moving Gaussians at their own frame
DEPTH_NUDGE = 0.02
#: the stage's colour learning rate over the main run's ``lr_sh`` (:func:`stage_optimizer`)
LR_SH_FACTOR = 8.0
#: alpha of the trained model's render below which its depth is not trusted (the prior's is used)
ALPHA_MIN_DEPTH = 0.5


def view_fade(means: torch.Tensor, origins: torch.Tensor, angle: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Opacity factor ``[L]`` of Gaussians at ``means [L, 3]`` with seed camera centres
    ``origins [L, 3]`` and angle scales ``angle [L]`` (radians; 0 = not view-bound: factor 1),
    seen from camera centre ``center [3]``: ``exp(-0.5 (sin(a) / angle)^2)``, ``a`` the angle
    at the Gaussian between the two rays (:func:`engine.geometry.camera.ray_parallax_sin`)."""
    bound = angle > 0
    s = ray_parallax_sin(means, origins, center.to(means)) / torch.where(bound, angle, torch.ones_like(angle))
    return torch.where(bound, torch.exp(-0.5 * s * s), torch.ones_like(s))


def wanted(cfg, model, data) -> bool:
    """Whether a run of ``cfg`` on ``data`` gets the shot-detail stage: ``cfg.shot_detail`` is
    on, the model has spline keys and the static / dynamic split, and the dynamic prior marks
    some training pixel moving."""
    if cfg.shot_detail != "on" or model.pos_keys is None or model.mlp is not None:
        return False
    if not model.is_split or data.fg is None:
        return False
    return bool((data.fg[data.train_idx] >= cfg.dynamic_threshold).any())


def detail_steps(cfg, data) -> int:
    """Steps of the stage: ``detail_steps_per_frame`` per training frame."""
    return int(math.ceil(cfg.detail_steps_per_frame * len(data.train_idx)))


def has_detail(model) -> bool:
    """Whether ``model`` already holds view-bound Gaussians (the stage has seeded them)."""
    return bool((model.gauss_view_angle > 0).any())


def seeds_per_frame(cfg, train_frames: int) -> int:
    """The most seeds a frame gets: ``detail_seeds``, fewer on a clip whose frames would
    together pass ``detail_seed_max`` (each seed is a row of every per-Gaussian tensor and its
    optimiser state for the rest of the run: 3,000 a frame over a 300-frame clip would be 900k)."""
    return max(1, min(cfg.detail_seeds, cfg.detail_seed_max // max(int(train_frames), 1)))


@torch.no_grad()
def seed_detail(model, data, cfg, gen: torch.Generator, render, opt: torch.optim.Adam) -> int:
    """Append the view-bound seeds of every training frame to ``model`` and to its optimiser
    ``opt`` (:func:`~engine.train.param_edit.edit_rows`; module docstring); returns how many.
    ``render(f)``: the trained model's :class:`~engine.raster.RenderOutput` of frame ``f`` at
    its own time (its depth places the seeds). One render per frame; the pixels of a frame are
    vectorised."""
    d, m = data, model
    gaps = torch.diff(torch.sort(d.times[d.train_idx]).values)
    # a one-frame clip has no frame interval: its seeds are always visible (lifespan 0)
    life = cfg.detail_lifespan_frames * float(gaps.median()) if len(gaps) else 0.0
    dyn_nodes = torch.nonzero(m.node_dyn).squeeze(1)
    per_frame = seeds_per_frame(cfg, len(d.train_idx))
    parts = []
    for f in d.train_idx.tolist():  # frames; a frame's pixels are vectorised
        moving = d.fg[f] >= cfg.dynamic_threshold
        ys, xs = torch.nonzero(moving, as_tuple=True)
        if len(ys) == 0:
            continue
        n = min(len(ys), per_frame)
        pick = distinct_pixels(len(ys), n, gen).to(ys.device)
        ys, xs = ys[pick], xs[pick]
        out = render(f)
        alpha = out.alpha[ys, xs, 0]
        z_model = out.depth[ys, xs, 0] / alpha.clamp_min(1e-6)
        z = torch.where(alpha >= ALPHA_MIN_DEPTH, z_model, d.depth[f][ys, xs] if d.depth is not None else z_model)
        ok = z > 0
        ys, xs, z = ys[ok], xs[ok], z[ok] * (1.0 - DEPTH_NUDGE)
        uv = torch.stack([xs.to(z.dtype) + 0.5, ys.to(z.dtype) + 0.5], -1)
        focal = float(d.K[f, 0, 0])
        footprint = math.sqrt(int(moving.sum()) / n)
        parts.append({
            "x": unproject(d.K[f], d.w2c[f], uv, z), "color": d.images[f, ys, xs],
            "scale": (0.5 * footprint * z / focal).unsqueeze(-1).expand(-1, 3),
            "t": torch.full_like(z, float(d.times[f])),
            "origin": camera_centers(d.w2c[f]).to(z).expand(len(z), 3),
            "angle": torch.full_like(z, cfg.detail_fade_px / (focal * cfg.detail_depth_error))})
    if not parts:
        return 0
    p = {k: torch.cat([q[k] for q in parts]) for k in parts[0]}
    g = len(p["x"])
    canon, bind_idx, bind_w = seed_frame_binding(m, p["x"], p["t"], dyn_nodes)
    quats = torch.zeros(g, 4, device=canon.device, dtype=canon.dtype)
    quats[:, 0] = 1
    extra = {"means": canon, "quats": quats, "log_scales": torch.log(p["scale"].clamp_min(1e-7)),
             "opacity_logits": inverse_sigmoid(torch.full((g,), cfg.detail_opacity, device=canon.device)),
             "sh_dc": ((p["color"].clamp(0, 1) - 0.5) / SH_C0).view(g, 1, 3),
             "sh_rest": torch.zeros(g, m.sh_rest.shape[1], 3, device=canon.device),
             "lifespan_log_scale": torch.zeros(g, device=canon.device)}
    buffers = {"gauss_dyn": torch.ones(g, dtype=torch.bool, device=canon.device), "gauss_t_center": p["t"],
               "gauss_lifespan": torch.full((g,), life, device=canon.device), "gauss_view_origin": p["origin"],
               "gauss_view_angle": p["angle"], "bind_idx": bind_idx, "bind_w": bind_w}
    rows = {name: torch.cat([getattr(m, name), value.to(getattr(m, name).dtype)]) for name, value in buffers.items()}
    edit_rows(m, opt, None, extra)  # the rows and their (zero) moments; the stage then builds its own Adam
    for name, value in rows.items():
        setattr(m, name, value.contiguous())
    return g


def seed_frame_binding(model, points: torch.Tensor, times: torch.Tensor, nodes: torch.Tensor):
    """Canonical centres ``[P, 3]`` and binding ``([P, K], [P, K])`` that put world ``points
    [P, 3]`` exactly where they were seen at ``times [P]``: each bound to its ``K`` nearest of
    ``nodes [S]`` (node ids) *as they are at its time* and moved back through the blend of those
    nodes' transforms (:func:`~engine.train.init_model.invert_at_time`). Why not
    :func:`~engine.train.init_model.canonicalise` (which rebinds in canonical space): a binding
    other than the one inverted does not bring a point back to its seed pixel (the stage's nodes
    do not train, so the binding need never change). One blend per distinct time."""
    view = NodeSubset(model, nodes)
    k = min(model.bind_k, len(nodes))
    canon = torch.empty_like(points)
    idx = torch.zeros(len(points), model.bind_k, dtype=torch.long, device=points.device)
    w = torch.zeros(len(points), model.bind_k, dtype=points.dtype, device=points.device)
    for t in torch.unique(times).tolist():  # one blend per frame
        sel = times == t
        canon[sel], i_t, w_t = invert_at_time(view, points[sel], t, k)
        idx[sel, :k], w[sel, :k] = nodes[i_t], w_t
    return canon, idx, w


def stage_optimizer(model, cfg) -> torch.optim.Adam:
    """The stage's Adam over the per-Gaussian appearance and shape (not the centres, not the
    nodes' keys); the trainer zeroes the gradient of every row that is not view-bound, and with
    fresh (zero) moments those rows do not move.

    Why the centres are not trained: a seed sits on its own pixel's ray, and what a few steps of
    one frame's photometric gradient do to its position is drift, not a fit (large scene 0,
    masked training views: 21.8 dB with the main run's ``lr_means``, 25.4 with the centres held).
    Why the colour learns at :data:`LR_SH_FACTOR` times ``lr_sh``: a seed sees ~15 steps, and the
    0.3 px low-pass of the projection spreads each seed over its neighbours' pixels, so the
    colours must move well away from the pixel colours they start at to give the frame back
    (x1 / 4 / 8 / 16: 25.4 / 27.5 / 28.4 / 27.8 dB, docs/benchmarks.md, *Shot detail*)."""
    groups = [{"name": "quats", "params": [model.quats], "lr": cfg.lr_quats},
              {"name": "log_scales", "params": [model.log_scales], "lr": cfg.lr_scales},
              {"name": "opacity_logits", "params": [model.opacity_logits], "lr": cfg.lr_opacity},
              {"name": "sh_dc", "params": [model.sh_dc], "lr": cfg.lr_sh * LR_SH_FACTOR},
              {"name": "sh_rest", "params": [model.sh_rest], "lr": cfg.lr_sh * LR_SH_FACTOR / 20}]
    fused = model.means.device.type in ("cpu", "cuda") and model.means.dtype == torch.float32
    return torch.optim.Adam(groups, eps=1e-15, fused=fused or None)


def keep_only_detail_grads_(model) -> None:
    """Zero the gradient of every row that is not view-bound (in place), so that the stage
    changes the seeds alone."""
    frozen = model.gauss_view_angle <= 0
    for name in ("quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        grad = getattr(model, name).grad
        if grad is not None:
            grad[frozen] = 0


#: pixels of the moving region's surroundings a stage step renders with it (:func:`moving_window`)
WINDOW_MARGIN = 8


def moving_window(moving: torch.Tensor, K: torch.Tensor, margin: int = WINDOW_MARGIN):
    """The window ``(y0, y1, x0, x1)`` of the image that holds the ``moving [H, W]`` pixels and
    ``margin`` pixels around them (clipped to the image; the whole image when nothing moves),
    and the intrinsics ``K [3, 3]`` of that window (principal point shifted).

    Why a stage step renders only this window: its seeds are on the moving pixels and only they
    learn, so the rest of the frame is the same render every time; the rasteriser still
    composites every Gaussian in the window by depth, as the full render does. On the large
    scenes a step costs about a third of a full-frame one (docs/benchmarks.md, *Shot detail*)."""
    h, w = moving.shape
    ys, xs = torch.nonzero(moving, as_tuple=True)
    if len(ys) == 0:
        return (0, h, 0, w), K
    y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + 1 + margin, h)
    x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + 1 + margin, w)
    K = K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return (y0, y1, x0, x1), K


def train_detail(trainer) -> None:
    """Run the stage on ``trainer`` (a :class:`~engine.train.trainer.Trainer` whose main
    training is done, ``trainer.step >= cfg.steps``): seed (unless a resumed checkpoint already
    holds the seeds), then train the seeds until ``cfg.steps + detail_steps``. Checkpoints,
    progress and a stop request work as in the main loop (a resume continues the stage)."""
    cfg, d, m = trainer.cfg, trainer.data, trainer.model
    end = cfg.steps + detail_steps(cfg, d)
    if trainer.step >= end or not wanted(cfg, m, d):
        return
    if not has_detail(m):
        count = seed_detail(m, d, cfg, trainer.gen, lambda f: render_frame(m, d, f, backend=cfg.backend), trainer.opt)
        trainer.opt = stage_optimizer(m, cfg)
        trainer.reporter.log(f"shot detail: {count} view-bound Gaussians on the moving pixels of "
                             f"{len(d.train_idx)} frames, {end - trainer.step} steps")
    train_idx = d.train_idx.cpu()
    windows = {}
    trainer.reporter.progress("detail", trainer.step - cfg.steps, end - cfg.steps)
    t0 = time.perf_counter()
    try:
        while trainer.step < end:
            if trainer._stop_requested:
                raise KeyboardInterrupt
            m = trainer.model
            f = epoch_frame(trainer.step - cfg.steps, train_idx, cfg.seed)
            t = float(d.times[f])
            shown = shown_gaussians(m, t)
            means_t, quats_t = m.deform(t, index=shown)
            if f not in windows:  # a frame's window is the same at every visit
                windows[f] = moving_window(d.fg[f] >= cfg.dynamic_threshold, d.K[f])
            (y0, y1, x0, x1), K = windows[f]
            out = render_scene(m, means_t, quats_t, K, d.w2c[f], x1 - x0, y1 - y0, backend=cfg.backend,
                               time=t, index=shown)
            target = d.images[f, y0:y1, x0:x1]
            loss = L.photometric(out.rgb, target, cfg.loss.ssim)
            trainer.opt.zero_grad(set_to_none=True)
            loss.backward()
            keep_only_detail_grads_(m)
            trainer.opt.step()
            trainer.step += 1
            s = trainer.step - cfg.steps
            if s % cfg.log_every == 0 or trainer.step == end:  # the PSNR of the frame's moving window
                psnr = float(L.psnr(out.rgb.detach().clamp(0, 1), target))
                trainer.reporter.progress("detail", s, end - cfg.steps, loss=float(loss.detach()), psnr=psnr)
            if cfg.checkpoint_every and trainer.step % cfg.checkpoint_every == 0 and trainer.step < end:
                trainer.train_seconds += time.perf_counter() - t0
                t0 = time.perf_counter()
                trainer.save_checkpoint()
    except KeyboardInterrupt:
        trainer.train_seconds += time.perf_counter() - t0
        path = trainer.save_checkpoint()
        raise Cancelled(f"training stopped at step {trainer.step} (shot detail); checkpoint saved to {path}") from None
    trainer.train_seconds += time.perf_counter() - t0
