"""Which training frame each step draws (engine/train/frame_order.py)."""

from __future__ import annotations

import pytest
import torch

from engine.errors import InputError
from engine.train.config import preset_config
from engine.train.frame_order import epoch_frame, resolve_frame_order, step_frame


def test_every_epoch_draws_every_training_frame_once_in_a_new_order():
    train_idx = torch.tensor([0, 2, 3, 5, 7, 8, 9, 12, 13])  # a holdout leaves gaps
    n = len(train_idx)
    epochs = [[epoch_frame(s, train_idx, seed=4) for s in range(e * n, (e + 1) * n)] for e in range(5)]
    for drawn in epochs:
        assert sorted(drawn) == train_idx.tolist()
    assert len({tuple(d) for d in epochs}) > 1  # reshuffled, not one fixed cycle
    # a function of (seed, step) alone: a resumed run draws what the uninterrupted one would
    assert [epoch_frame(s, train_idx, seed=4) for s in range(17, 40)] == sum(epochs, [])[17:40]
    other = [epoch_frame(s, train_idx, seed=5) for s in range(3 * n)]
    assert other != sum(epochs[:3], [])


def test_uniform_draws_from_the_runs_generator_and_epochs_spread_the_visits():
    train_idx = torch.arange(52)
    gen = torch.Generator().manual_seed(0)
    uniform = [step_frame("uniform", s, train_idx, 0, gen) for s in range(600)]
    epochs = [step_frame("epochs", s, train_idx, 0, gen) for s in range(600)]
    visits = lambda drawn: torch.bincount(torch.tensor(drawn), minlength=52)  # noqa: E731
    # 600 steps over 52 frames: 11 or 12 visits each, where independent draws leave some frames far fewer
    assert int(visits(epochs).min()) == 11 and int(visits(epochs).max()) == 12
    assert int(visits(uniform).min()) < 8
    with pytest.raises(InputError, match="frame_order"):
        preset_config("preview", frame_order="sequential")


def test_auto_shuffles_epochs_only_for_a_run_with_lifespans():
    assert preset_config("preview").frame_order == "auto"
    assert resolve_frame_order("auto", lifespans=True) == "epochs"
    assert resolve_frame_order("auto", lifespans=False) == "uniform"
    assert resolve_frame_order("epochs", lifespans=False) == "epochs"
    assert resolve_frame_order("uniform", lifespans=True) == "uniform"
    with pytest.raises(ValueError, match="frame_order"):
        resolve_frame_order("sequential", lifespans=True)
