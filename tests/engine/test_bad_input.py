"""Bad input never costs data or memory (issues #19, #22).

Every case is a new user's mistake run through the CLI's ``main(argv)`` in-process: it
must end in ONE ``error:`` line that names the file or option (``needle``), exit
non-zero, leave every earlier file byte-identical and leave no temporary files. Cases
that could exhaust memory run in a child process under ``RLIMIT_AS``
(:func:`test_bounded_memory`).
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from engine.cli import main

from . import _bad_input_fixtures as fx


def _cfg(tmp, obj) -> str:
    p = tmp / "cfg.json"
    p.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return str(p)


def _train(tmp, clip, *extra):
    return ["train", str(clip), "--out", str(tmp / "out"), *extra]


def _bundle_cmd(tmp, cmd, edit=None, *extra):
    b = fx.bundle(tmp / "b")
    if edit:
        edit(b)
    args = {"render": [str(tmp / "r")], "eval": [], "export": ["--ply", str(tmp / "x.ply")]}
    out = ["--out"] + args[cmd] if cmd == "render" else args[cmd]
    return [cmd, str(b), *out, *extra]


def _scene_edit(fn):
    return lambda b: fx.edit_json(b / "scene.json", fn)


def _cam0(key, value):
    def fn(s):
        s["cameras"][0][key] = value
    return _scene_edit(fn)


def _manifest_nan_fps(t):
    p = fx.manifest(t / "m")
    p.write_text(p.read_text().replace('"fps": 24.0', '"fps": NaN'))
    return _train(t, p)


def _readonly_out(t):
    ro = t / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    return ["train", str(fx.manifest(t / "m")), "--out", str(ro / "out")]


def _file_parent_out(t):
    (t / "afile").write_text("x")
    return ["export", str(fx.bundle(t / "b")), "--ply", str(t / "afile" / "x.ply")]


def _overwrite_missing_clip(t):
    b = fx.bundle(t / "out")
    (b / "eval.json").write_text("{}")
    (b / "report").mkdir()
    (b / "report" / "report.html").write_text("<html></html>")
    return ["train", str(t / "missing"), "--out", str(b), "--overwrite"]


def _n3dv(t, shape, value=0.0):
    root = t / "n3dv"
    root.mkdir()
    np.save(root / "poses_bounds.npy", np.full(shape, value))
    for i in range(shape[0]):
        fx.video(root / f"cam{i:02d}.mp4")
    return root


def _overwrite_bad_clip(t):
    argv = _overwrite_missing_clip(t)
    argv[1] = str(fx.manifest(t / "m", fps=-1))
    return argv


def _out_is_input(t):
    d = fx.nerfies(t / "ds")
    return ["train", str(d), "--out", str(d), "--overwrite"]


def _nerfies(edit):
    return lambda t: _train(t, fx.nerfies(t / "ds", edit))


def _meta(fn):
    return lambda root: fx.edit_json(root / "metadata.json", fn)


def _ds(fn):
    return lambda root: fx.edit_json(root / "dataset.json", fn)


def _set(key, value):
    def fn(d):
        d[next(iter(d))][key] = value
    return fn


def _cam_path(t, **over):
    cam = dict(frame=1, width=fx.W, height=fx.H, **fx.camera())
    cam.update(over)
    p = t / "path.json"
    p.write_text(json.dumps({"format": "motion-splats-camera-path", "version": 1, "cameras": [cam]}))
    return str(p)


def _truncate(name, keep):
    def fn(b):
        raw = (b / name).read_bytes()
        (b / name).write_bytes(raw[:keep])
    return fn


def _disk_full(t):
    import errno

    import engine.fsutil

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    b = fx.bundle(t / "b")
    _disk_full.patch = (engine.fsutil.os, "fsync", full)
    return ["export", str(b), "--ply", str(t / "x.ply")]


def _finetune_bad_config(t):
    b = fx.bundle(t / "b")
    fx.edit_json(b / "scene.json", lambda s: s["config"].update(lr_means="fast"))
    return ["finetune", str(b), "--steps", "1"]


def _render_nonempty(t):
    (t / "r").mkdir()
    (t / "r" / "keep.png").write_bytes(b"x")
    return _bundle_cmd(t, "render")


def _pickle_checkpoint(t):
    import torch

    class Payload:
        def __reduce__(self):
            return (os.system, ("touch " + str(t / "PWNED"),))

    b = fx.bundle(t / "out")
    fx.edit_json(b / "scene.json", lambda s: s.update(stage="init"))
    (b / "checkpoints").mkdir()
    torch.save({"x": Payload()}, b / "checkpoints" / "checkpoint.pt")
    return ["train", str(fx.manifest(t / "m")), "--out", str(b), "--resume", "--steps", "10"]


CASES = {
    # ------------------------------------------------------------- clips
    "missing clip": (lambda t: _train(t, t / "nope"), "nope"),
    "empty folder": (lambda t: (t / "e").mkdir() or _train(t, t / "e"), "e: folder is not a recognised"),
    "text file named .mp4": (lambda t: (t / "v.mp4").write_text("hello") and _train(t, t / "v.mp4"), "v.mp4"),
    "truncated video": (lambda t: _train(t, _truncated_video(t)), "v.avi"),
    "one-frame video": (lambda t: _train(t, fx.video(t / "one.avi", n=1)), "one.avi"),
    "one-image folder": (lambda t: (t / "i").mkdir() or fx.cv2.imwrite(str(t / "i" / "a.png"), fx.frames(1)[0])
                         and _train(t, t / "i"), "only 1 image"),
    "unsupported file": (lambda t: (t / "a.txt").write_text("x") and _train(t, t / "a.txt"), "a.txt"),
    "mixed image sizes": (lambda t: _train(t, fx.image_folder(t / "imgs", {3: (32, 24)}), "--fov", "50"), "0003.png"),
    # ------------------------------------------------------------- manifests
    "manifest invalid JSON": (lambda t: (t / "c.json").write_text('{"format": "motion-splats-clip",')
                              and _train(t, t / "c.json"), "c.json"),
    "manifest width string": (lambda t: _train(t, fx.manifest(t / "m", width="64")), "'width'"),
    "manifest NaN fps": (_manifest_nan_fps, "'fps'"),
    "manifest singular rotation": (lambda t: _train(t, fx.manifest(t / "m", cameras=[
        dict(frame=i + 1, K=fx.camera()["K"], w2c=np.diag([1, 1, 0, 1.0]).tolist()) for i in range(fx.F)])),
        "clip.json"),
    "manifest negative focal": (lambda t: _train(t, fx.manifest(t / "m", cameras=[
        dict(frame=i + 1, **fx.camera(-50)) for i in range(fx.F)])), "focal"),
    "manifest path escapes": (lambda t: _train(t, fx.manifest(t / "m", frames=["../../../../etc/passwd"] * fx.F)),
                              "outside"),
    "manifest video escapes": (lambda t: _train(t, fx.manifest(t / "m", frames=None, video="/etc/passwd")),
                               "outside"),
    "manifest priors unknown name": (lambda t: _train(t, fx.manifest(t / "m", priors={"normals": "n.npy"})),
                                     "'priors'"),
    "overwrite with a bad manifest": (lambda t: _overwrite_bad_clip(t), "'fps'"),
    "manifest priors not a map": (lambda t: _train(t, fx.manifest(t / "m", priors=["depth.npy"])), "'priors'"),
    # ------------------------------------------------------------- datasets
    "dnerf angle string": (lambda t: _train(t, fx.dnerf(t / "d", camera_angle_x="wide")), "camera_angle_x"),
    "dnerf time string": (lambda t: _train(t, fx.dnerf(t / "d", frame_time="late")), "time"),
    "dnerf w string": (lambda t: _train(t, fx.dnerf(t / "d", w="wide")), "transforms_train.json"),
    "nerfies metadata list": (_nerfies(lambda r: (r / "metadata.json").write_text("[]")), "metadata.json"),
    "nerfies time_id x": (_nerfies(_meta(_set("time_id", "x"))), "metadata.json"),
    "nerfies train_ids 5": (_nerfies(_ds(lambda d: d.update(train_ids=5))), "dataset.json"),
    "nerfies camera focal string": (_nerfies(lambda r: fx.edit_json(r / "camera" / "left_000000.json",
                                                                    lambda c: c.update(focal_length="f"))),
                                    "left_000000.json"),
    "n3dv poses wrong shape": (lambda t: _train(t, _n3dv(t, (4, 7))), "poses_bounds.npy"),
    "n3dv poses NaN": (lambda t: _train(t, _n3dv(t, (2, 17), np.nan)), "poses_bounds.npy"),
    "colmap 4-byte points3D.bin": (lambda t: _train(t, fx.colmap(t / "c")), "points3D.bin"),
    "nerfies scene.json list": (_nerfies(lambda r: (r / "scene.json").write_text("[1]")), "scene.json"),
    # ------------------------------------------------------------- configs and options
    "config unknown key": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"stepz": 3})), "stepz"),
    "config not an object": (lambda t: _train(t, t / "x", "--config", _cfg(t, [1])), "cfg.json"),
    "config NaN": (lambda t: _train(t, t / "x", "--config", _cfg(t, '{"lr_means": NaN}')), "lr_means"),
    "config loss Infinity": (lambda t: _train(t, t / "x", "--config", _cfg(t, '{"loss": {"depth": Infinity}}')),
                             "depth"),
    "config log_every 0": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"log_every": 0})), "log_every"),
    "config bool string": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"node_densify": "maybe"})),
                           "node_densify"),
    "config width 100000": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"width": 100000})), "width"),
    "config steps 1e12": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"steps": 10**12})), "steps"),
    "config gaussians 1e9": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"gaussians_per_frame": 10**9})),
                             "gaussians_per_frame"),
    "config float for int": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"steps": 2.5})), "steps"),
    "config names the file": (lambda t: _train(t, t / "x", "--config", _cfg(t, {"seed": "one"})), "cfg.json"),
    "inline config unknown key": (lambda t: _train(t, t / "x", "--config", '{"stepz": 3}'), "stepz"),
    "inline config broken": (lambda t: _train(t, t / "x", "--config", '{"steps": 3'), "--config"),
    "--steps 1e12": (lambda t: _train(t, t / "x", "--steps", str(10**12)), "steps"),
    "--threads -1": (lambda t: ["version", "--threads", "-1"], "--threads"),
    # ------------------------------------------------------------- output folders
    "out is a file": (lambda t: (t / "f").write_text("x") and ["train", str(fx.manifest(t / "m")), "--out",
                                                             str(t / "f")], "not a folder"),
    "out read-only": (_readonly_out, "ro"),
    "out parent is a file": (_file_parent_out, "afile"),
    "overwrite with missing clip": (_overwrite_missing_clip, "missing"),
    "out equals input": (_out_is_input, "input"),
    "resume pickle checkpoint": (_pickle_checkpoint, "checkpoint.pt"),
    "disk full": (_disk_full, "free disk space"),
    # ------------------------------------------------------------- bundles
    "scene.json truncated": (lambda t: _bundle_cmd(t, "render", _truncate("scene.json", 40)), "scene.json"),
    "scene.json a list": (lambda t: _bundle_cmd(t, "render", lambda b: (b / "scene.json").write_text("[]")),
                          "scene.json"),
    "nodes.npz truncated": (lambda t: _bundle_cmd(t, "render", _truncate("nodes.npz", 100)), "nodes.npz"),
    "nodes.npz text": (lambda t: _bundle_cmd(t, "export", lambda b: (b / "nodes.npz").write_text("x")),
                       "nodes.npz"),
    "ply count word": (lambda t: _bundle_cmd(t, "render", lambda b: fx.ply_with_header(
        b / "gaussians.ply", lambda h: h.replace(b"vertex 200", b"vertex many"))), "gaussians.ply"),
    "ply count negative": (lambda t: _bundle_cmd(t, "render", lambda b: fx.ply_with_header(
        b / "gaussians.ply", lambda h: h.replace(b"vertex 200", b"vertex -5"))), "gaussians.ply"),
    "ply no newline": (lambda t: _bundle_cmd(t, "render", lambda b: (b / "gaussians.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nend_header")), "gaussians.ply"),
    "ply truncated": (lambda t: _bundle_cmd(t, "render", _truncate("gaussians.ply", 900)), "gaussians.ply"),
    "ply NaN opacity": (lambda t: _bundle_cmd(t, "render", lambda b: fx.ply_column(b / "gaussians.ply", "opacity",
                                                                                   np.nan)), "opacity"),
    "ply inf colour": (lambda t: _bundle_cmd(t, "export", lambda b: fx.ply_column(b / "gaussians.ply", "f_dc",
                                                                                  np.inf)), "gaussians.ply"),
    "ply NaN rotation": (lambda t: _bundle_cmd(t, "render", lambda b: fx.ply_column(b / "gaussians.ply", "rot_1",
                                                                                    np.nan)), "rot"),
    "ply huge scale": (lambda t: _bundle_cmd(t, "render", lambda b: fx.ply_column(b / "gaussians.ply", "scale_0",
                                                                                  80.0)), "scale"),
    "scene negative focal": (lambda t: _bundle_cmd(t, "render", _cam0("K", [[-50, 0, 32], [0, -50, 24], [0, 0, 1]])),
                             "focal"),
    "scene singular w2c": (lambda t: _bundle_cmd(t, "render", _cam0("w2c", np.diag([1, 1, 0, 1.0]).tolist())),
                           "w2c"),
    "scene huge image": (lambda t: _bundle_cmd(t, "render", _cam0("width", 10**6)), "width"),
    "render --frames garbage": (lambda t: _bundle_cmd(t, "render", None, "--frames", "1-x"), "--frames"),
    "render --frames huge": (lambda t: _bundle_cmd(t, "render", None, "--frames", "1-3000000"), "--frames"),
    "render --frames outside": (lambda t: _bundle_cmd(t, "render", None, "--frames", "500-600"), "--frames"),
    "render --time nan": (lambda t: _bundle_cmd(t, "render", None, "--time", "nan"), "--time"),
    "render --time 2": (lambda t: _bundle_cmd(t, "render", None, "--time", "2"), "--time"),
    "render --camera missing": (lambda t: _bundle_cmd(t, "render", None, "--camera", str(t / "p.json")), "p.json"),
    "render --camera huge": (lambda t: _bundle_cmd(t, "render", None, "--camera", _cam_path(t, width=10**6,
                                                                                              height=10**6)),
                             "path.json"),
    "render --camera negative focal": (lambda t: _bundle_cmd(t, "render", None, "--camera", _cam_path(
        t, K=[[-50, 0, 32], [0, 50, 24], [0, 0, 1]])), "path.json"),
    "render into non-empty": (_render_nonempty, "--overwrite"),
    "finetune bad bundle config": (_finetune_bad_config, "lr_means"),
    "export nothing": (lambda t: ["export", str(fx.bundle(t / "b"))], "--ply"),
}


def _truncated_video(t):
    v = fx.video(t / "full.avi")
    (t / "v.avi").write_bytes(v.read_bytes()[:300])
    v.unlink()
    return t / "v.avi"


def _snapshot(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _temp_files(root: Path) -> list[str]:
    # fsutil.atomic_path's temporaries: ".<name>.<random><suffix>"
    return [str(p) for p in root.rglob(".*") if p.is_file()]


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_one_clear_line(name, tmp_path, capsys, monkeypatch):
    build, needle = CASES[name]
    work = tmp_path / "w"
    work.mkdir()
    monkeypatch.chdir(work)

    def tripwire(*a, **k):  # every case must be refused before the priors stage (seconds, not minutes)
        raise AssertionError("bad input reached the priors stage")

    import engine.pipeline

    monkeypatch.setattr(engine.pipeline, "prepare", tripwire)
    argv = build(work)
    patch = getattr(build, "patch", None)
    if patch:
        monkeypatch.setattr(*patch)
    if name == "out read-only" and os.geteuid() == 0:
        pytest.skip("root ignores folder permissions")
    before = _snapshot(work)
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: usage + one error line, exit 2
        code = exc.code
    finally:
        for p in work.rglob("*"):  # let tmp_path cleanup remove read-only test folders
            if p.is_dir():
                p.chmod(0o755)
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("error:") or "rror" in ln]
    assert code not in (0, None), (name, err)
    assert "Traceback" not in err, err
    assert len(lines) == 1, err
    assert needle in lines[0], (needle, lines[0])
    assert "weights_only=False" not in err and "--resume" not in lines[0] or name.startswith("resume"), err
    after = _snapshot(work)
    changed = [k for k, v in before.items() if after.get(k) != v]
    assert not changed, f"earlier files changed or lost: {changed}"
    assert not _temp_files(work), _temp_files(work)
    assert not (work / "PWNED").exists()


# ------------------------------------------------------------------------ memory-bounded
MEMORY_CASES = {
    "manifest frame_end 1e9 with a video": (
        lambda t: _train(t, _manifest_video(t, frame_end=10**9)), "frame_end"),
    "camera path of 1e6 x 1e6 px": (
        lambda t: _bundle_cmd(t, "render", None, "--camera", _cam_path(t, width=10**6, height=10**6)), "path.json"),
    "render 3 million frames": (lambda t: _bundle_cmd(t, "render", None, "--frames", "1-3000000"), "--frames"),
}


def _manifest_video(t, **over):
    root = t / "mv"
    root.mkdir()
    fx.video(root / "v.avi")
    m = {"format": "motion-splats-clip", "version": 1, "video": "v.avi", "frames": None, "frame_start": 1,
         "frame_end": fx.F, "fps": 24.0, "width": fx.W, "height": fx.H, "cameras": None}
    m.update(over)
    (root / "clip.json").write_text(json.dumps(m))
    return root / "clip.json"


_LIMIT = 3 << 30  # 3 GiB of address space: torch + numba import fine, no runaway allocation


def _limit():
    resource.setrlimit(resource.RLIMIT_AS, (_LIMIT, _LIMIT))


@pytest.mark.parametrize("name", list(MEMORY_CASES))
def test_bounded_memory(name, tmp_path):
    build, needle = MEMORY_CASES[name]
    argv = build(tmp_path)
    res = subprocess.run([sys.executable, "-m", "engine", *argv], cwd=fx.REPO, capture_output=True, text=True,
                         timeout=120, preexec_fn=_limit)
    assert res.returncode == 2, res.stderr[-2000:]
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr[-2000:]
