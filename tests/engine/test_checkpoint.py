"""Checkpoint identity, finished runs and byte-exact resume from a periodic checkpoint."""

import pickle
import shutil

import pytest
import torch

from engine import bundle as B
from engine.errors import InputError
from engine.train.config import preset_config
from engine.train.trainer import Trainer

from .synthetic_training import make_nodes, make_scene


def _cfg(**kw):
    base = dict(steps=60, gaussians_per_frame=400, init_keyframes=4, num_nodes=25, densify_from=20,
                densify_until=50, densify_every=15, checkpoint_every=25, log_every=10, warmup_static_steps=10)
    base.update(kw)
    return preset_config("preview", **base)


@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=12, width=48, height=36)


class _Killed(Exception):
    """Stands in for SIGKILL: nothing of the trainer's own interrupt handling runs."""


def _die_at(trainer, step):
    original = trainer._loss

    def loss(f):
        if trainer.step == step:
            raise _Killed
        return original(f)

    trainer._loss = loss


@pytest.mark.slow
def test_resume_from_periodic_checkpoint_is_byte_identical(tmp_path, scene):
    data, truth = scene
    Trainer(data, make_nodes(truth), _cfg(), tmp_path / "full").run()
    part = Trainer(data, make_nodes(truth), _cfg(), tmp_path / "part")
    _die_at(part, 40)  # killed after the step-25 checkpoint: only that one is left
    with pytest.raises(_Killed):
        part.run()
    assert torch.load(tmp_path / "part/checkpoints/checkpoint.pt", weights_only=True)["step"] == 25
    resumed = Trainer(data, make_nodes(truth), _cfg(), tmp_path / "part", resume=True)
    assert resumed.step == 25
    resumed.run()
    a = (tmp_path / "full" / B.GAUSSIANS_FILE).read_bytes()
    b = (tmp_path / "part" / B.GAUSSIANS_FILE).read_bytes()
    assert a == b
    assert (tmp_path / "full" / B.NODES_FILE).exists()


def test_finished_run_drops_its_checkpoint_and_refuses_resume(tmp_path, scene):
    data, truth = scene
    Trainer(data, make_nodes(truth), _cfg(steps=30), tmp_path / "run").run()
    assert not (tmp_path / "run" / "checkpoints").exists()
    assert B.finished_steps(tmp_path / "run") == 30
    before = (tmp_path / "run" / B.GAUSSIANS_FILE).read_bytes()
    with pytest.raises(InputError, match="finished run"):
        B.check_output_dir(tmp_path / "run", resume=True)
    with pytest.raises(InputError, match="finished run"):
        Trainer(data, make_nodes(truth), _cfg(steps=30), tmp_path / "run", resume=True)
    assert (tmp_path / "run" / B.GAUSSIANS_FILE).read_bytes() == before
    B.check_output_dir(tmp_path / "run", overwrite=True, resume=True)  # --overwrite still may


@pytest.fixture(scope="module")
def _killed_run(tmp_path_factory, scene):
    data, truth = scene
    run = tmp_path_factory.mktemp("killed") / "run"
    t = Trainer(data, make_nodes(truth), _cfg(), run)
    _die_at(t, 30)
    with pytest.raises(_Killed):
        t.train()
    return run


@pytest.fixture
def interrupted(tmp_path, _killed_run):
    """A run stopped at step 30 by a kill: its step-25 checkpoint is on disk (a fresh copy per test)."""
    shutil.copytree(_killed_run, tmp_path / "run")
    return tmp_path / "run"


@pytest.mark.parametrize("change,needle", [
    (dict(sh_degree=2), "different training config"),
    (dict(motion="mlp"), "different training config"),
    (dict(seed=3), "different training config"),
])
def test_resume_refuses_another_config(interrupted, scene, change, needle):
    data, truth = scene
    with pytest.raises(InputError, match=needle) as err:
        Trainer(data, make_nodes(truth), _cfg(**change), interrupted, resume=True)
    assert "checkpoint.pt" in str(err.value)


def test_resume_refuses_other_frames(interrupted):
    other, truth = make_scene(frames=12, width=40, height=30)  # another --width
    with pytest.raises(InputError, match="different frames"):
        Trainer(other, make_nodes(truth), _cfg(), interrupted, resume=True)


def test_resume_allows_another_device_setting(interrupted, scene):
    data, truth = scene
    t = Trainer(data, make_nodes(truth), _cfg(device="cpu", log_every=5), interrupted, resume=True)
    assert t.step == 25


def _rewrite(path, edit):
    state = torch.load(path, weights_only=True)
    edit(state)
    torch.save(state, path)


@pytest.mark.parametrize("edit,needle", [
    (lambda s: s.pop("optimizer"), "lacks \\['optimizer'\\]"),
    (lambda s: s["model"].pop("means"), "does not match this run's model"),
])
def test_incomplete_checkpoint_is_one_line(interrupted, scene, edit, needle):
    data, truth = scene
    _rewrite(interrupted / "checkpoints/checkpoint.pt", edit)
    with pytest.raises(InputError, match=needle):
        Trainer(data, make_nodes(truth), _cfg(), interrupted, resume=True)


class _Payload:
    def __reduce__(self):
        return (print, ("pickle payload ran",))


def test_pickle_payload_is_refused_without_suggesting_weights_only_false(interrupted, scene, capsys):
    data, truth = scene
    ck = interrupted / "checkpoints/checkpoint.pt"
    torch.save({"step": 1, "x": _Payload()}, ck, pickle_protocol=pickle.DEFAULT_PROTOCOL)
    with pytest.raises(InputError) as err:
        Trainer(data, make_nodes(truth), _cfg(), interrupted, resume=True)
    assert "weights_only" not in str(err.value) and "objects other than tensors" in str(err.value)
    assert "pickle payload ran" not in capsys.readouterr().out
