"""`engine eval` and the HTML report on a tiny bundle trained on the bpy `tiny` synthetic scene."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it

REPO = Path(__file__).resolve().parents[2]
PY = sys.executable


def _run(args, timeout=240):
    return subprocess.run([PY, *args], cwd=REPO, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(clip dir, bundle dir) of a 20-step preview run on the tiny synthetic scene."""
    pytest.importorskip("bpy")
    root = tmp_path_factory.mktemp("evalrep")
    gen = _run(["tools/synth_scene.py", "--out", str(root / "clip"), "--preset", "tiny", "--quiet"])
    assert gen.returncode == 0, gen.stderr[-2000:]
    clip = Path(json.loads(gen.stdout.strip().splitlines()[-1])["out"])
    out = root / "bundle"
    tr = _run(["-m", "engine", "train", str(clip), "--out", str(out), "--steps", "20", "--jsonl",
               "--cache", str(root / "cache")])
    assert tr.returncode == 0, tr.stdout[-2000:] + tr.stderr[-2000:]
    result = [json.loads(l) for l in tr.stdout.splitlines() if l.startswith("{")][-1]
    assert result["event"] == "result"
    return clip, out, result


def _lpips_model(path: Path):
    """A stand-in LPIPS: mean |a - b| of two [1,3,H,W] inputs -> [1,1,1,1]."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    a = helper.make_tensor_value_info("a", TensorProto.FLOAT, [1, 3, "H", "W"])
    b = helper.make_tensor_value_info("b", TensorProto.FLOAT, [1, 3, "H", "W"])
    d = helper.make_tensor_value_info("d", TensorProto.FLOAT, [1, 1, 1, 1])
    nodes = [helper.make_node("Sub", ["a", "b"], ["s"]), helper.make_node("Abs", ["s"], ["abs"]),
             helper.make_node("ReduceMean", ["abs"], ["d"], axes=[1, 2, 3], keepdims=1)]
    graph = helper.make_graph(nodes, "l1", [a, b], [d])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def test_train_writes_report(trained):
    clip, out, result = trained
    html = Path(result["report"])
    assert html == out / "report" / "report.html" and html.is_file()
    text = html.read_text(encoding="utf-8")
    srcs = re.findall(r'src="([^"]+)"', text)
    assert any("render" in s for s in srcs) and any("_gt" in s for s in srcs) and "nodes_overlay.png" in srcs
    for s in srcs:  # self-contained: every image lies next to the HTML
        assert (html.parent / s).is_file(), s
    assert "<svg" in text and "polyline" in text and "Config" in text


def test_eval_metrics_and_json(trained):
    clip, out, result = trained
    r = _run(["-m", "engine", "eval", str(out), "--jsonl"])
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    ev = [json.loads(l) for l in r.stdout.splitlines() if l.startswith("{")][-1]
    assert ev["event"] == "result"
    mean = ev["mean"]
    for key in ("frames", "psnr", "ssim", "masked_psnr", "masked_ssim", "lpips"):
        assert key in mean
    assert mean["lpips"] is None and any("pass --lpips-onnx" in n for n in ev["notes"])
    assert mean["frames"] == len(ev["frames"]) > 0
    assert 5 < mean["psnr"] < 60 and 0 < mean["ssim"] <= 1
    # same renders and metric as the trainer's own held-out evaluation
    assert mean["psnr"] == pytest.approx(result["eval"]["psnr"], abs=0.05)
    saved = json.loads((out / "eval.json").read_text())
    assert saved["mean"]["psnr"] == pytest.approx(mean["psnr"])


def test_eval_lpips_onnx_and_moved_clip(trained, tmp_path):
    clip, out, _ = trained
    model = _lpips_model(tmp_path / "l1.onnx")
    from engine.commands.eval import evaluate_bundle

    res = evaluate_bundle(out, lpips_onnx=model, write=False)
    vals = [f["lpips"] for f in res["frames"]]
    assert all(isinstance(v, float) and 0 < v < 2 for v in vals)
    assert res["mean"]["lpips"] == pytest.approx(np.mean(vals))
    # the clip moved: clear error naming the path and --clip; --clip fixes it
    moved = tmp_path / "moved_clip"
    clip.rename(moved)
    try:
        r = _run(["-m", "engine", "eval", str(out), "--jsonl"])
        assert r.returncode == 2
        err = [json.loads(l) for l in r.stdout.splitlines() if l.startswith("{")][-1]
        assert err["event"] == "error" and str(clip) in err["path"] and "--clip" in err["fix"]
        res2 = evaluate_bundle(out, clip_path=moved, write=False)
        assert res2["mean"]["psnr"] == pytest.approx(res["mean"]["psnr"], abs=1e-4)
    finally:
        moved.rename(clip)


def test_report_command(trained, tmp_path):
    _, out, _ = trained
    target = tmp_path / "r" / "report.html"
    r = _run(["-m", "engine", "report", str(out), "--out", str(target), "--jsonl"])
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert target.is_file() and (target.parent / "nodes_overlay.png").is_file()


def test_report_names_what_gave_moving_objects_their_depth():
    from engine.report import _prior_rows

    rows = _prior_rows({"depth": {"backend": "sparse", "moving_objects": "contact", "hinges": 1},
                        "flow": {"backend": "dis"}})
    assert rows[0][:3] == ["depth", "sparse; moving objects: contact, 1 hinge(s)", "weight-free"]
    assert rows[1][:3] == ["flow", "dis", "weight-free"]


def test_report_says_a_depth_model_was_checked_or_set_aside():
    from engine.report import _prior_rows

    aside = _prior_rows({"depth": {"backend": "sparse", "moving_objects": "contact", "check": {"ratio": 1.14},
                                   "set_aside": {"backend": "onnx", "model": "pydnet"}}})
    assert aside[0][1].endswith("depth model pydnet set aside (its error at triangulated static points 1.14x a "
                                "flat depth's)") and aside[0][2] == "weight-free"
    kept = _prior_rows({"depth": {"backend": "onnx", "model": "dav2", "check": {"ratio": 0.41}}})
    assert kept[0][1:3] == ["onnx; checked: error at triangulated static points 0.41x a flat depth's", "dav2"]
