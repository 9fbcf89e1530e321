"""Gaussian lifespans: moving Gaussians visible around the frame they were seeded from.

Why: with a fixed camera the moving things of a clip (hands, cups) get their dynamic
Gaussians seeded on every training frame, and node paths that follow them only a few frames
(the weight-free tracks end on fast or textureless parts). A Gaussian that is right at its
own frame is then wrong at most others, and the optimiser's compromise is to make it nearly
transparent (median opacity of the dynamic Gaussians 0.10 on ``cups.mp4``, 0.22 for the
static ones): the moving things render as ghosts. A lifespan lets each one be opaque where it
is right. With a moving camera and the weight-free depth, a moving Gaussian seen from many
positions over time is what pulls a moving part that floats (a pendulum arm, whose ground
contact is the wall behind it) toward its depth: with lifespans the training views and frames
along the shot's path gain (bedroom.mp4: training +2.35 dB, withheld -0.1, the children solid
instead of ghosts) but a second camera loses (the generated vrig scene's: -1.2 dB in the
moving masks; with ground-truth depth lifespans win there too, docs/benchmarks.md). So
``auto`` gives lifespans unless the camera translates *and* the clip comes with held-out
cameras of its own (``TrainingData.held_out_cameras``: a dataset made to be seen from
elsewhere); a plain video, whatever its camera does, gets them.

The window is ``exp(-0.5 ((t - t_center) / lifespan)^2)`` on the opacity
(:meth:`engine.train.model.DynamicScene.opacities_at`); a lifespan of 0 is always visible.
The bundle stores both per Gaussian (``nodes.npz`` ``gauss_t_center`` / ``gauss_lifespan``)
and the Blender preview applies the same window per frame.

Each moving Gaussian's lifespan is learned (``lifespan_log_scale``, ``TrainConfig.lr_lifespan``),
within ``lifespan_min`` .. ``lifespan_max`` times the seeded one (:func:`clamp_lifespans_`).
Why: one lifespan for all is a compromise between the parts whose nodes follow them (a torso,
a slow cup: a long life is right and fills the frames between) and the fast ones whose nodes
lose them within a frame (a cup swept across the table): there a Gaussian shown at the
neighbouring frames sits off the object, the loss of those frames keeps its opacity low, and
the fast object renders as scattered, faint fragments on its own frame too. Learned, the fast
part's Gaussians shorten their lives and turn opaque (cups.mp4: training frames +1.8 dB,
withheld +0.3 dB over 3 seeds, docs/benchmarks.md).
"""

from __future__ import annotations

import math

import torch

from ..geometry.camera import FIXED_CAMERA_TOL, camera_translates  # noqa: F401 (re-exported)
from .config import LIFESPAN_MODES


def lifespan_window(t: float, t_center: torch.Tensor, lifespan: torch.Tensor) -> torch.Tensor:
    """Opacity factor [G] at engine time ``t``: ``exp(-0.5 ((t - t_center) / lifespan)^2)``
    where ``lifespan [G] > 0``, 1 where it is 0 (``t_center [G]``)."""
    live = lifespan > 0
    z = (t - t_center) / torch.where(live, lifespan, torch.ones_like(lifespan))
    return torch.where(live, torch.exp(-0.5 * z * z), torch.ones_like(z))


#: the rasteriser's alpha floor (``engine/raster``: a Gaussian whose opacity is below it draws
#: nothing and gets no gradient from the render)
ALPHA_MIN = 1.0 / 255.0


def shown_gaussians(model, t: float, max_share: float = 0.9) -> torch.Tensor | None:
    """Rows ``[L]`` (ascending) of the Gaussians of ``model`` (a
    :class:`~engine.train.model.DynamicScene`) a render at engine time ``t`` can show: opacity
    at ``t`` (:meth:`~engine.train.model.DynamicScene.opacities_at`) at least the rasteriser's
    :data:`ALPHA_MIN`; None when that is more than ``max_share`` of them (the gathers would cost
    more than they save) or the model has no lifespans.

    Why: with lifespans most moving Gaussians of a long clip are outside their window at any one
    time (whole cups.mp4: ~85 % of 129k), yet the step deformed, coloured, projected and
    back-propagated all of them. Every backend skips a Gaussian whose alpha stays below the
    floor, so leaving them out of the step's render changes no pixel and no gradient of the
    render (``tests/engine/test_lifespan.py``). The window is evaluated only where it can reach
    the floor: opacity <= 1 needs ``|t - t_center| <= sqrt(2 ln 255) lifespan``, bounded with
    the longest learned lifespan factor, so the step pays a few comparisons per Gaussian, not
    exponentials."""
    m = model
    if not bool((m.gauss_lifespan > 0).any()):
        return None
    with torch.no_grad():
        # (a 0.1 % margin for rounding: the exact test below decides)
        reach = 1.001 * math.sqrt(2.0 * math.log(1.0 / ALPHA_MIN)) * float(torch.exp(m.lifespan_log_scale.max()))
        near = (m.gauss_lifespan <= 0) | ((float(t) - m.gauss_t_center).abs() <= reach * m.gauss_lifespan)
        rows = torch.nonzero(near).squeeze(1)
        shown = rows[m.opacities_at(t, index=rows) >= ALPHA_MIN]
    if len(shown) > max_share * m.num_gaussians:
        return None
    return shown


def lifespan_seed_count(cfg, train_frames: int = 0) -> int:
    """Moving Gaussians a run with lifespans seeds over ``train_frames`` training frames:
    ``dynamic_gaussians`` x ``lifespan_seed_factor`` (with lifespans a frame shows only the moving
    Gaussians seeded around it), times ``train_frames / lifespan_seed_frames`` when the clip is
    longer than that. Why the last factor: the seeds are spread over the frames, so a whole
    300-frame clip got a fifth of the moving Gaussians per frame a 60-frame preview gets, and
    its moving things rendered as soft blobs (cups.mp4, 262 training frames: 91 seeds a frame
    against 460 at 60 frames; with the same per frame, training frames +1.55 dB, withheld +0.81,
    docs/benchmarks.md). The growth stops at ``lifespan_seed_max`` in all (never below the
    short clip's count): every Gaussian costs step time whether its window shows it or not, so an
    uncapped 2000-frame clip would seed 800k and train ~6x slower a step."""
    base = cfg.dynamic_gaussians * cfg.lifespan_seed_factor
    per_clip = base
    if cfg.lifespan_seed_frames > 0 and train_frames > cfg.lifespan_seed_frames:
        per_clip = max(base, min(base * train_frames / cfg.lifespan_seed_frames, cfg.lifespan_seed_max))
    return int(round(per_clip))


def gaussian_budget(cfg, model, train_frames: int = 0) -> int:
    """The densification cap: ``cfg.max_gaussians``, raised by the extra moving seeds when the
    model's Gaussians have lifespans (:func:`lifespan_seed_count` over ``train_frames``). Why: the
    extra seeds are per-frame capacity, not refinement, and without the raise they filled the cap
    before the first densification (cups.mp4: 32.6k seeds against 30k, nothing densified; with the
    headroom a run without lifespans has, training frames +5.69 -> +5.90 dB over 3 seeds at 3x the
    seeds, docs/benchmarks.md)."""
    extra = (lifespan_seed_count(cfg, train_frames) - cfg.dynamic_gaussians
             if bool((model.gauss_lifespan > 0).any()) else 0)
    return int(cfg.max_gaussians + max(extra, 0))


def resolve_lifespan(mode: str, frames: float, train_times: torch.Tensor, train_w2c: torch.Tensor,
                     extent: float, held_out_cameras: bool = True) -> float:
    """The lifespan (engine time) the moving Gaussians get, 0 for none.

    ``mode`` 'on' | 'off' | 'auto' (on unless the training cameras translate,
    :func:`camera_translates`, and the clip has ``held_out_cameras``; module docstring);
    ``frames`` = the lifespan in training-frame intervals (the median gap between the sorted
    ``train_times [F]``).
    """
    if mode not in LIFESPAN_MODES:
        raise ValueError(f"lifespan must be one of {LIFESPAN_MODES}, not {mode!r}")
    if mode == "off" or frames <= 0 or len(train_times) < 2:
        return 0.0
    if mode == "auto" and held_out_cameras and camera_translates(train_w2c, extent):
        return 0.0
    gap = torch.diff(torch.sort(train_times.flatten()).values).median()
    return float(frames * gap)


def data_lifespan(cfg, data) -> float:
    """:func:`resolve_lifespan` for training ``data`` (a :class:`~engine.train.data.TrainingData`)
    under ``cfg``: its training frames' times and cameras, extent and held-out cameras. The one
    call the initial model (``engine.train.init_model``) and :func:`run_has_lifespans` share, so
    that the two decisions cannot part."""
    train = data.train_idx
    return resolve_lifespan(cfg.lifespan, cfg.lifespan_frames, data.times[train], data.w2c[train], data.extent,
                            data.held_out_cameras)


def run_has_lifespans(cfg, data) -> bool:
    """Whether training ``data`` (a :class:`~engine.train.data.TrainingData`) under ``cfg`` gives
    its moving Gaussians lifespans: the static / dynamic split is on, the dynamic prior calls
    some training pixel moving, and :func:`resolve_lifespan` is positive. The split itself is
    decided on the nodes (``engine.train.init_model``); this is the same decision on the prior
    the nodes' flags come from, made before any model exists (the step count depends on it:
    :func:`engine.train.config.steps_per_frame`)."""
    if not cfg.split or data.fg is None:
        return False
    train = data.train_idx.to(data.fg.device)
    if not bool((data.fg[train] >= cfg.dynamic_threshold).any()):
        return False
    return data_lifespan(cfg, data) > 0


@torch.no_grad()
def clamp_lifespans_(model, cfg) -> None:
    """Keep every learned lifespan within ``cfg.lifespan_min`` .. ``cfg.lifespan_max`` times its
    seeded one (in place on ``model.lifespan_log_scale [G]``; a projection after each optimiser
    step, so the model itself needs no config)."""
    model.lifespan_log_scale.clamp_(math.log(cfg.lifespan_min), math.log(cfg.lifespan_max))
