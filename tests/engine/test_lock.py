"""One writer per --out folder (engine/lock.py), stale temporaries, file modes (engine/fsutil.py)."""

import json
import os
import socket
import stat
import subprocess
import sys

import pytest

from engine import fsutil
from engine.cli import main
from engine.errors import InputError
from engine.lock import LOCK_NAME, acquire, hold, release

from . import _bad_input_fixtures as fx


def _lock_of(folder, pid):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / LOCK_NAME).write_text(json.dumps({"pid": pid, "host": socket.gethostname()}))


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_second_writer_is_refused_while_the_first_lives(tmp_path):
    _lock_of(tmp_path / "out", os.getppid())  # a live process that is not us
    with pytest.raises(InputError, match="another engine command"):
        acquire(tmp_path / "out")
    assert (tmp_path / "out" / LOCK_NAME).exists()  # the holder's lock is untouched


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    _lock_of(tmp_path / "out", _dead_pid())
    path = acquire(tmp_path / "out")
    assert json.loads(path.read_text())["pid"] == os.getpid()
    release(path)
    assert not path.exists()


def test_hold_releases_on_error_and_removes_a_folder_it_created(tmp_path):
    with pytest.raises(RuntimeError):
        with hold(tmp_path / "new"):
            assert (tmp_path / "new" / LOCK_NAME).exists()
            raise RuntimeError
    assert not (tmp_path / "new").exists()
    (tmp_path / "kept").mkdir()
    with hold(tmp_path / "kept"):
        pass
    assert (tmp_path / "kept").is_dir() and not list((tmp_path / "kept").iterdir())


def test_cli_train_refuses_a_locked_out_folder(tmp_path, capsys):
    clip = fx.manifest(tmp_path / "m")
    _lock_of(tmp_path / "out", os.getppid())
    code = main(["train", str(clip), "--out", str(tmp_path / "out"), "--steps", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "another engine command" in err[0] and "out" in err[0]


def test_stale_temporaries_are_cleaned_when_the_lock_is_taken(tmp_path):
    out = tmp_path / "out"
    (out / "checkpoints").mkdir(parents=True)
    stale = [out / ".scene.json.ab12_x9z.json", out / "checkpoints" / ".checkpoint.pt.0a1b2c3d.pt",
             out / ".gaussians.ply.zz99yy88.ply"]
    keep = [out / ".bashrc", out / "scene.json", out / ".notes.txt"]
    for p in stale + keep:
        p.write_text("x")
    with hold(out):
        pass
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in keep)


def test_atomic_writes_respect_the_umask(tmp_path):
    path = tmp_path / "a.json"
    fsutil.atomic_write_json(path, {"a": 1})
    mode = stat.S_IMODE(path.stat().st_mode)
    assert mode == 0o666 & ~fsutil._UMASK  # not mkstemp's 0600 (unless the umask itself says so)


def test_finetune_refuses_a_bundle_another_command_writes(tmp_path, capsys):
    b = fx.bundle(tmp_path / "b")
    _lock_of(b, os.getppid())
    before = (b / "gaussians.ply").read_bytes()
    code = main(["finetune", str(b), "--steps", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "another engine command" in err[0]
    assert (b / "gaussians.ply").read_bytes() == before and not (b / "backups").exists()


def test_interrupted_render_does_not_suggest_resume(tmp_path, capsys, monkeypatch):
    import engine.commands.render as render

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(render, "cameras_for_frames", interrupted)
    code = main(["render", str(fx.bundle(tmp_path / "b")), "--out", str(tmp_path / "r"), "--jsonl"])
    event = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 130 and event["event"] == "error" and event["fix"] == "run the command again"
