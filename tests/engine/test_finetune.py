"""`engine finetune`: appearance trained with the (edited) motion locked.

A 20-step preview run on the bpy `tiny` synthetic scene, its node splines edited the way
Blender's Send edits writes them (moved keys, broken incoming tangents), then fine-tuned:
``nodes.npz`` and the Gaussian centres stay bit for bit, appearance changes, the
training-view PSNR does not get worse, earlier results are backed up or left alone.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from engine import bundle as B

REPO = Path(__file__).resolve().parents[2]


def _run(args, timeout=300):
    return subprocess.run([sys.executable, *map(str, args)], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def _events(stdout):
    return [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    pytest.importorskip("bpy")
    root = tmp_path_factory.mktemp("finetune")
    gen = _run(["tools/synth_scene.py", "--out", root / "clip", "--preset", "tiny", "--quiet"])
    assert gen.returncode == 0, gen.stderr[-2000:]
    clip = Path(json.loads(gen.stdout.strip().splitlines()[-1])["out"])
    out = root / "bundle"
    tr = _run(["-m", "engine", "train", clip, "--out", out, "--steps", "20", "--jsonl", "--cache", root / "cache"])
    assert tr.returncode == 0, tr.stdout[-2000:] + tr.stderr[-2000:]
    # an artist's edit: shift one node's keys and break its incoming position tangents
    nodes = B.read_nodes(out / B.NODES_FILE)
    pos = nodes.pos_keys.copy()
    pos[0] += np.float32(0.05)
    nodes.pos_keys = pos
    nodes.pos_tangents_in = nodes.pos_tangents * np.float32(0.5)
    nodes.rot_tangents_in = nodes.rot_tangents.copy()
    B.write_nodes(out / B.NODES_FILE, nodes)
    return clip, out


def _copy_bundle(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("cache", "checkpoints", "report"))
    return dst


@pytest.mark.slow
def test_finetune_in_place_locks_motion_and_backs_up(trained, tmp_path):
    _, src = trained
    bundle = _copy_bundle(src, tmp_path / "b")
    nodes_bytes = (bundle / B.NODES_FILE).read_bytes()
    before = B.load_bundle(bundle)
    ply_bytes = (bundle / B.GAUSSIANS_FILE).read_bytes()
    r = _run(["-m", "engine", "finetune", bundle, "--steps", "25", "--jsonl"])
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    events = _events(r.stdout)
    res = events[-1]
    assert res["event"] == "result", res
    assert any(e["event"] == "progress" and e.get("stage") == "finetune" for e in events)
    assert res["steps"] == 25 and res["bundle"] == str(bundle)
    # motion: the edited splines and the centres are untouched, bit for bit
    assert (bundle / B.NODES_FILE).read_bytes() == nodes_bytes
    after = B.load_bundle(bundle)
    assert after.nodes.pos_tangents_in is not None
    assert np.array_equal(after.gaussians.means, before.gaussians.means)
    # appearance changed, and the PSNR on the training views is not worse
    assert not res["kept_original"]
    assert res["psnr_after"] >= res["psnr_before"], res
    assert not np.array_equal(after.gaussians.sh, before.gaussians.sh)
    assert not np.array_equal(after.gaussians.opacity_logits, before.gaussians.opacity_logits)
    # the replaced files are backed up; scene.json records the fine-tune
    backup = Path(res["backup"])
    assert backup.parent == bundle / "backups"
    assert (backup / B.GAUSSIANS_FILE).read_bytes() == ply_bytes
    assert json.loads((backup / B.SCENE_FILE).read_text())["stats"] == before.scene["stats"]
    ft = after.scene["stats"]["finetune"]
    assert len(ft) == 1 and ft[0]["steps"] == 25
    # the engine renders the fine-tuned bundle with the edited motion
    rr = _run(["-m", "engine", "render", bundle, "--frames", "1", "--out", tmp_path / "r", "--quiet"])
    assert rr.returncode == 0, rr.stderr[-2000:]


@pytest.mark.slow
def test_finetune_to_new_bundle_leaves_input(trained, tmp_path):
    _, src = trained
    bundle = _copy_bundle(src, tmp_path / "b")
    snapshot = {p.name: p.read_bytes() for p in bundle.iterdir() if p.is_file()}
    out = tmp_path / "ft"
    r = _run(["-m", "engine", "finetune", bundle, "--steps", "5", "--out", out, "--jsonl"])
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert {p.name: p.read_bytes() for p in bundle.iterdir() if p.is_file()} == snapshot
    assert not (bundle / "backups").exists()
    assert (out / B.NODES_FILE).read_bytes() == snapshot[B.NODES_FILE]
    assert np.array_equal(B.read_ply(out / B.GAUSSIANS_FILE).means, B.read_ply(bundle / B.GAUSSIANS_FILE).means)
    # never over an earlier result without --overwrite
    again = _run(["-m", "engine", "finetune", bundle, "--steps", "1", "--out", out, "--jsonl"])
    assert again.returncode == 2
    err = _events(again.stdout)[-1]
    assert err["event"] == "error" and "--overwrite" in err["message"]


def test_finetune_bad_input_is_a_clear_error(tmp_path):
    r = _run(["-m", "engine", "finetune", tmp_path / "missing", "--jsonl"])
    assert r.returncode == 2
    err = _events(r.stdout)[-1]
    assert err["event"] == "error" and "bundle folder not found" in err["message"]
    assert "Traceback" not in r.stderr


@pytest.mark.slow
def test_finetune_cancel_changes_nothing(trained, tmp_path):
    import signal

    _, src = trained
    bundle = _copy_bundle(src, tmp_path / "b")
    snapshot = {p.name: p.read_bytes() for p in bundle.iterdir() if p.is_file()}
    proc = subprocess.Popen([sys.executable, "-m", "engine", "finetune", str(bundle), "--steps", "100000",
                             "--jsonl"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        for line in proc.stdout:  # wait until the optimisation runs
            if '"stage": "finetune"' in line:
                break
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    err = _events(out)[-1]
    assert err["event"] == "error" and "not changed" in err["message"]
    assert {p.name: p.read_bytes() for p in bundle.iterdir() if p.is_file()} == snapshot
    assert not (bundle / "backups").exists()


def test_backup_is_all_or_nothing(tmp_path, monkeypatch):
    """A full disk while backing up leaves no truncated backup that looks complete."""
    import errno
    import shutil

    from engine.commands.finetune import _backup

    for name in ("gaussians.ply", "scene.json"):
        (tmp_path / name).write_text(name)
    real = shutil.copy2

    def copy2(src, dst, **kw):
        if str(src).endswith("scene.json"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst, **kw)

    monkeypatch.setattr(shutil, "copy2", copy2)
    with pytest.raises(OSError):
        _backup(tmp_path, ["gaussians.ply", "scene.json"])
    assert not (tmp_path / "backups").exists() or not list((tmp_path / "backups").iterdir())
    monkeypatch.setattr(shutil, "copy2", real)
    dest = _backup(tmp_path, ["gaussians.ply", "scene.json"])
    assert sorted(p.name for p in dest.iterdir()) == ["gaussians.ply", "scene.json"]
