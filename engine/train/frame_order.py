"""Which training frame each step draws.

Why not a uniform draw per step: with lifespans (:mod:`.lifespan`) a frame's moving Gaussians
learn only on the steps that draw that frame or its neighbours, so how often each frame is
drawn decides how far its moving things get. 600 independent draws over 52 frames give each
frame 11.5 on average but only 5-7 to a few (Poisson spread), and those frames' hands and cups
stay ghosts. ``epochs`` draws every training frame once per ``len(train_idx)`` steps, in an
order shuffled anew each epoch: every frame gets its share. Measured on cups.mp4 / bedroom.mp4
(60 frames, ``--holdout 8``, preview): training frames +0.3 to +0.6 dB over the uniform draw,
withheld frames +0.1 (docs/benchmarks.md, *Steps per frame*).

Without lifespans every Gaussian learns from every frame, and the shuffled epochs measured no
better than independent draws on the generated large-motion scenes (masked held-out -0.13 dB over
6 paired runs, within about a run's spread), so ``auto`` keeps the uniform draw there: the order
matters where a frame's own visits do.

The order is a function of ``(seed, step)`` alone (each epoch's permutation comes from its own
generator seeded with the run's seed and the epoch number), so a run resumed from a checkpoint
at any step draws exactly the frames the uninterrupted run would, with no sampler state to save.
"""

from __future__ import annotations

import torch

from .config import FRAME_ORDERS

# mixes the run's seed with the epoch number into one generator seed (a large odd constant:
# consecutive epochs of nearby seeds never share a permutation generator)
_EPOCH_STRIDE = 1_000_003


def epoch_frame(step: int, train_idx: torch.Tensor, seed: int) -> int:
    """The training frame of step ``step`` under the ``epochs`` order.

    Parameters
    ----------
    step : int
        Training step, >= 0.
    train_idx : torch.Tensor
        ``[F]`` int64, the training frames' indices into the clip (CPU).
    seed : int
        The run's seed (``TrainConfig.seed``).

    Returns
    -------
    int
        An element of ``train_idx``; steps ``e * F .. (e + 1) * F - 1`` draw every element once.
    """
    n = int(train_idx.shape[0])
    epoch, within = divmod(int(step), n)
    gen = torch.Generator().manual_seed(int(seed) * _EPOCH_STRIDE + epoch)
    return int(train_idx[torch.randperm(n, generator=gen)[within]])


def resolve_frame_order(order: str, lifespans: bool) -> str:
    """``order`` with ``auto`` decided: ``epochs`` when the run's moving Gaussians have
    ``lifespans`` (``DynamicScene.gauss_lifespan > 0`` somewhere), else ``uniform``."""
    if order not in FRAME_ORDERS:
        raise ValueError(f"frame_order must be one of {FRAME_ORDERS}, not {order!r}")
    if order == "auto":
        return "epochs" if lifespans else "uniform"
    return order


def step_frame(order: str, step: int, train_idx: torch.Tensor, seed: int, gen: torch.Generator) -> int:
    """The training frame of step ``step``: :func:`epoch_frame` for ``order == "epochs"``, a
    uniform draw from ``gen`` for ``"uniform"`` (the only order before 2026-11-27); ``order``
    as :func:`resolve_frame_order` returns it."""
    if order == "epochs":
        return epoch_frame(step, train_idx, seed)
    return int(train_idx[torch.randint(0, len(train_idx), (1,), generator=gen)])
