"""Configs written by older versions still load (#19): keys that nothing read were removed
from TrainConfig and are ignored with one warning; any other unknown key is still refused."""

from __future__ import annotations

import dataclasses
import logging

import pytest

from engine.errors import InputError
from engine.train.config import REMOVED_KEYS, TrainConfig


def test_an_old_bundle_config_with_removed_keys_loads_with_a_warning(caplog):
    old = TrainConfig().to_dict()
    old.update({"batch_frames": 1, "eval_every": 0})
    with caplog.at_level(logging.WARNING, logger="engine.train.config"):
        cfg = TrainConfig.from_dict(old, "scene.json")
    assert cfg == TrainConfig()
    lines = [r.getMessage() for r in caplog.records if r.name == "engine.train.config"]
    assert len(lines) == 2 and all("no longer used" in ln and "scene.json" in ln for ln in lines)


def test_removed_keys_are_gone_and_unknown_keys_still_refused():
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    assert not names & set(REMOVED_KEYS)
    with pytest.raises(InputError, match="unknown config key 'batch_frame'"):
        TrainConfig.from_dict({"batch_frame": 1})
