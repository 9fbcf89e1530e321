"""Interrupting `engine train` (SIGINT / SIGTERM / SIGKILL in the priors, node and training
stages) always leaves a resumable state and no temporary files, and `--resume` then
writes the same gaussians.ply, byte for byte, as the uninterrupted run (issues #19, #22).

Each case is a real child process on a tiny generated clip (6 frames, 64x48, 60 steps,
checkpoint every 20), signalled when its JSON-lines progress reaches the named stage.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from engine import bundle as B

from . import _bad_input_fixtures as fx

pytestmark = pytest.mark.slow

CONFIG = dict(gaussians_per_frame=300, init_keyframes=3, num_nodes=16, densify_from=10, densify_until=30,
              densify_every=10, checkpoint_every=20, log_every=5, warmup_static_steps=5)


def _argv(root: Path, out: Path, *extra) -> list[str]:
    return [sys.executable, "-m", "engine", "train", str(root / "m" / "clip.json"), "--out", str(out), "--steps",
            "60", "--width", "64", "--config", str(root / "cfg.json"), "--no-models", "--jsonl", *extra]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("interrupt")
    fx.manifest(root / "m")
    (root / "cfg.json").write_text(json.dumps(CONFIG))
    res = subprocess.run(_argv(root, root / "full"), cwd=fx.REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return root


def _run_until(argv, stage: str, min_step: int, sig: int) -> tuple[int, list[dict]]:
    """Start ``argv``; send ``sig`` at the first progress event of ``stage`` with step >= ``min_step``."""
    proc = subprocess.Popen(argv, cwd=fx.REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    events, sent = [], False
    for line in proc.stdout:
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        events.append(ev)
        if not sent and ev.get("event") == "progress" and ev.get("stage") == stage and ev.get("step", 0) >= min_step:
            proc.send_signal(sig)
            sent = True
    proc.wait(timeout=300)
    proc.stderr.close()
    assert sent, f"stage {stage!r} never reached step {min_step}"
    return proc.returncode, events


def _temporaries(folder: Path) -> list[Path]:
    return [p for p in folder.rglob(".*") if p.is_file() and p.name != ".motion-splats.lock"]


CASES = [  # (signal, stage, step at which it is sent)
    (signal.SIGINT, "train", 25),    # mid-training: stops at a step boundary, checkpoints, exit 130
    (signal.SIGTERM, "nodes", 0),    # node initialisation: nothing to checkpoint yet
    (signal.SIGKILL, "train", 30),   # no handler runs: the step-20 periodic checkpoint is what is left
    (signal.SIGKILL, "load frames", 1),  # priors stage, before any bundle file
]


@pytest.mark.parametrize("sig,stage,step", CASES, ids=[f"{s.name}-{st}" for s, st, _ in CASES])
def test_interrupted_run_resumes_to_the_same_bytes(workspace, tmp_path, sig, stage, step):
    out = tmp_path / "out"
    code, events = _run_until(_argv(workspace, out), stage, step, sig)
    assert code == (-9 if sig == signal.SIGKILL else 130), events[-3:]
    if sig != signal.SIGKILL:
        assert events[-1]["event"] == "error", events[-3:]  # the one line saying it stopped
        assert not (out / ".motion-splats.lock").exists()  # released by the handler
    assert not _temporaries(out), _temporaries(out)
    if sig == signal.SIGKILL and stage == "train":
        # a kill while a checkpoint was being written leaves its temporary beside the
        # previous checkpoint (os.replace never ran): plant one, the resume must clean it
        ck = out / "checkpoints" / "checkpoint.pt"
        (ck.parent / ".checkpoint.pt.k1ll3d00.pt").write_bytes(ck.read_bytes()[:1000])
    if (out / B.SCENE_FILE).exists():
        B.load_bundle(out)  # whatever is on disk is a loadable bundle
    res = subprocess.run(_argv(workspace, out, "--resume"), cwd=fx.REPO, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert (out / B.GAUSSIANS_FILE).read_bytes() == (workspace / "full" / B.GAUSSIANS_FILE).read_bytes()
    assert not _temporaries(out) and not (out / "checkpoints" / "checkpoint.pt").exists()
    # the finished bundle refuses a second --resume in one line instead of retraining
    again = subprocess.run(_argv(workspace, out, "--resume"), cwd=fx.REPO, capture_output=True, text=True,
                           timeout=300)
    assert again.returncode == 2 and "finished run" in again.stdout
