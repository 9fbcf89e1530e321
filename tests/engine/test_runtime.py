"""Process-wide torch state is set where the process starts, never by library objects (#19)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import torch

from engine.train.config import preset_config
from engine.train.trainer import Trainer

from .synthetic_training import make_nodes, make_scene

REPO = Path(__file__).resolve().parents[2]


def test_constructing_a_trainer_leaves_deterministic_mode_alone(tmp_path):
    data, truth = make_scene(frames=4, width=32, height=24)
    cfg = preset_config("preview", steps=2, gaussians_per_frame=50, init_keyframes=2, num_nodes=25, densify_until=0,
                        checkpoint_every=0)
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(False)
    try:
        Trainer(data, make_nodes(truth), cfg, tmp_path / "run")
        assert not torch.are_deterministic_algorithms_enabled()
    finally:
        torch.use_deterministic_algorithms(before, warn_only=True)


def _probe(command: list[str]) -> str:
    code = ("import sys, torch, engine.cli as cli\n"
            "seen = {}\n"
            "class Probe:\n"
            "    HELP = 'probe'\n"
            "    @staticmethod\n"
            "    def add_arguments(p): p.add_argument('--device')\n"
            "    @staticmethod\n"
            "    def run(args, reporter):\n"
            "        print('DET', torch.are_deterministic_algorithms_enabled(), torch.get_num_threads())\n"
            "import importlib, types\n"
            "real = importlib.import_module\n"
            "cli.importlib = types.SimpleNamespace(import_module=lambda name, package=None: "
            "Probe if name == '.commands.train' else real(name, package))\n"
            f"sys.exit(cli.main({command!r}))\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_the_cli_sets_threads_and_deterministic_cpu_mode_at_start():
    # a command's run() already sees the process-wide settings (the library sets none)
    assert "DET True 1" in _probe(["train", "--threads", "1", "--device", "cpu"])
