"""The ``--depth-model`` path: output convention (inverse vs larger = farther), the input-size
rule for models with dynamic H, W, per-frame scale/shift alignment to the anchors; a tiny
model built by the test and the real PyDNet from ``../shared/models`` when present."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from engine.errors import InputError
from engine.priors import estimate_depth
from engine.priors.onnx_util import dynamic_input_size, parse_settings

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
PYDNET = SHARED / "models" / "pydnet_mobile2019_depth.onnx"
CUPS = SHARED / "data" / "clips" / "cups.mp4"


def _tiny_depth(path):
    """Dynamic H, W; output ``depth`` = mean of the RGB input (larger = farther when the frame is
    painted with its depth). H and W must be multiples of 64: a 64x64 average pool upsampled x64
    (times 0) is added, which only broadcasts when the pool grid covers the whole input."""
    nodes = [
        helper.make_node("ReduceMean", ["image", "ax"], ["m"], keepdims=1),
        helper.make_node("AveragePool", ["m"], ["p"], kernel_shape=[64, 64], strides=[64, 64]),
        helper.make_node("Resize", ["p", "", "sc"], ["u"], mode="nearest"),
        helper.make_node("Mul", ["u", "zero"], ["z"]),
        helper.make_node("Add", ["m", "z"], ["depth"]),
    ]
    graph = helper.make_graph(
        nodes, "depth", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, "H", "W"])],
        [numpy_helper.from_array(np.array([1], np.int64), "ax"),
         numpy_helper.from_array(np.array([1, 1, 64, 64], np.float32), "sc"),
         numpy_helper.from_array(np.array(0.0, np.float32), "zero")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _clip(F=3, H=90, W=150):
    """Frames whose brightness is an affine function of the true depth (a smooth ramp with a
    near 'object' that moves), plus exact anchors on the static part."""
    ys, xs = np.mgrid[0:H, 0:W]
    depth = np.empty((F, H, W), np.float32)
    frames = np.empty((F, H, W, 3), np.uint8)
    anchors = []
    for f in range(F):
        d = 2.0 + 2.0 * ys / H + 0.5 * xs / W  # background: floor-like ramp
        obj = (np.abs(xs - 40 - 30 * f) < 12) & (np.abs(ys - 45) < 12)
        d = np.where(obj, 1.5, d)
        depth[f] = d
        frames[f] = np.clip((d - 1.0) * 60, 0, 255).astype(np.uint8)[..., None]
        sel = ~obj & (xs % 9 == 0) & (ys % 9 == 0)
        anchors.append(np.stack([xs[sel] + 0.5, ys[sel] + 0.5, d[sel]], 1).astype(np.float32))
    return frames, depth, anchors


def _K(F, H, W):
    return np.tile(np.array([[W, 0, W / 2], [0, W, H / 2], [0, 0, 1.0]]), (F, 1, 1)), np.tile(np.eye(4), (F, 1, 1))


def test_dynamic_input_size_rounds_to_the_multiple():
    assert dynamic_input_size(448, 640, 640, 64) == (448, 640)
    assert dynamic_input_size(90, 150, 150, 64) == (64, 128)
    assert dynamic_input_size(180, 240, 320, 64) == (256, 320)
    assert dynamic_input_size(10, 400, 100, 64) == (64, 128)  # at least one multiple per side


def test_larger_is_farther_model_aligned_to_anchors(tmp_path):
    model = _tiny_depth(tmp_path / "d.onnx")
    (tmp_path / "d.onnx.json").write_text(json.dumps({"size_multiple": 64, "mean": [0, 0, 0], "std": [1, 1, 1]}))
    frames, gt, anchors = _clip()
    K, w2c = _K(*gt.shape)
    dep, conf = estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, max_width=150, output="depth")
    inner = np.zeros_like(gt, bool); inner[:, 8:-8, 8:-8] = True  # resampling blurs the border
    rel = np.abs(dep - gt) / gt
    assert np.median(rel[inner]) < 0.02
    obj = gt == 1.5
    assert np.median(rel[obj & inner]) < 0.05  # the moving object has a depth of its own
    # read as inverse depth (the default) the same prediction is wrong
    inv, _ = estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, max_width=150)
    assert np.median((np.abs(inv - gt) / gt)[inner]) > 3 * np.median(rel[inner])
    # the sidecar can say it too
    (tmp_path / "d.onnx.json").write_text(json.dumps({"size_multiple": 64, "mean": [0, 0, 0], "std": [1, 1, 1],
                                                       "output": "depth"}))
    dep2, _ = estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, max_width=150)
    assert np.allclose(dep2, dep)


def test_settings_given_without_a_sidecar_file_match_the_file(tmp_path):
    # a model in a read-only folder: the same keys given to the priors instead of a file beside it
    model = _tiny_depth(tmp_path / "d.onnx")
    settings = {"size_multiple": 64, "mean": [0, 0, 0], "std": [1, 1, 1], "output": "depth"}
    frames, gt, anchors = _clip(F=2)
    K, w2c = _K(*gt.shape)
    given, _ = estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, max_width=150, settings=settings)
    (tmp_path / "d.onnx.json").write_text(json.dumps(settings))
    from_file, _ = estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, max_width=150)
    assert np.array_equal(given, from_file)
    # laid over the file key by key: the given output wins
    inv, _ = estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, max_width=150,
                            settings={"output": "inverse"})
    assert not np.allclose(inv, from_file)
    with pytest.raises(InputError) as e:
        estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, settings={"size_multipel": 64})
    assert "size_multipel" in str(e.value) and "d.onnx" in str(e.value)


def test_settings_from_the_command_line(tmp_path):
    assert parse_settings('{"size_multiple": 64, "mean": [0, 0, 0]}') == {"size_multiple": 64, "mean": [0, 0, 0]}
    f = tmp_path / "pydnet.json"
    f.write_text('{"size_multiple": 64}')
    assert parse_settings(str(f)) == {"size_multiple": 64}
    for bad, words in (("{size_multiple: 64}", "not valid JSON"), ("[64]", "must be a JSON object"),
                       ('{"multiple": 64}', "unknown setting")):
        with pytest.raises(InputError) as e:
            parse_settings(bad)
        assert words in str(e.value) and "--depth-sidecar" in str(e.value)
    f.write_text("{oops")
    with pytest.raises(InputError) as e:
        parse_settings(str(f))
    assert "pydnet.json" in str(e.value)


def test_unknown_depth_output_is_one_clear_error(tmp_path):
    model = _tiny_depth(tmp_path / "d.onnx")
    frames, gt, anchors = _clip(F=1)
    K, w2c = _K(*gt.shape)
    with pytest.raises(InputError) as e:
        estimate_depth(frames, K, w2c, "onnx", str(model), anchors=anchors, output="disparity")
    assert "d.onnx" in str(e.value)


@pytest.mark.skipif(not (PYDNET.is_file() and CUPS.is_file()), reason="../shared PyDNet / cups.mp4 not present")
def test_real_pydnet_sees_the_table_nearer_than_the_wall(tmp_path):
    # the research-only weights are linked into a temp folder (never copied into the repo) with
    # the sidecar their contract needs: RGB/255, H and W multiples of 64, larger = farther
    os.symlink(PYDNET, tmp_path / "pydnet.onnx")
    (tmp_path / "pydnet.onnx.json").write_text(json.dumps({"size_multiple": 64, "mean": [0, 0, 0],
                                                            "std": [1, 1, 1], "output": "depth"}))
    cap = cv2.VideoCapture(str(CUPS))
    ok, bgr = cap.read()
    cap.release()
    assert ok
    frame = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), (320, 180), interpolation=cv2.INTER_AREA)[None]
    K, w2c = _K(1, 180, 320)
    dep, conf = estimate_depth(frame, K, w2c, "onnx", str(tmp_path / "pydnet.onnx"),
                               anchors=[np.zeros((0, 3), np.float32)], max_width=320)
    assert dep.shape == (1, 180, 320) and np.isfinite(dep).all() and (dep > 0).all()
    # cups.mp4 looks down at a table: the bottom rows (table edge) are nearer than the top rows
    assert np.median(dep[0, -30:]) < 0.9 * np.median(dep[0, :30])
