"""ONNX backends of the priors, with tiny models built by onnx.helper and run by onnxruntime."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from engine.errors import InputError
from engine.priors import dynamic_mask, estimate_depth, extract_tokens
from engine.priors.onnx_util import IMAGENET_MEAN, IMAGENET_STD, prepare_images


def _save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _tiny_vit(path, size=28, p=14, D=6, seed=0):
    wgt = np.random.default_rng(seed).normal(size=(D, 3, p, p)).astype(np.float32)
    g = size // p
    nodes = [
        helper.make_node("Conv", ["input_image", "w"], ["feat"], kernel_shape=[p, p], strides=[p, p]),
        helper.make_node("Reshape", ["feat", "shape"], ["flat"]),
        helper.make_node("Transpose", ["flat"], ["tok"], perm=[0, 2, 1]),
        helper.make_node("ReduceMean", ["tok", "axes"], ["cls"], keepdims=1),
        helper.make_node("Concat", ["cls", "tok"], ["out"], axis=1),
    ]
    graph = helper.make_graph(
        nodes, "vit",
        [helper.make_tensor_value_info("input_image", TensorProto.FLOAT, ["B", 3, size, size])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, ["B", 1 + g * g, D])],
        [numpy_helper.from_array(wgt, "w"), numpy_helper.from_array(np.array([0, D, g * g], np.int64), "shape"),
         numpy_helper.from_array(np.array([1], np.int64), "axes")])
    return _save(graph, path), wgt


def test_onnx_tokens_match_manual_patch_projection(tmp_path):
    path, wgt = _tiny_vit(tmp_path / "vit.onnx")
    frames = np.random.default_rng(1).integers(0, 255, (3, 40, 60, 3), dtype=np.uint8)
    grid = extract_tokens(frames, backend="onnx", model_path=path, patch_size=14)
    assert grid.tokens.shape == (3, 2, 2, 6) and grid.tokens.dtype == np.float32
    assert np.allclose(np.linalg.norm(grid.tokens, axis=-1), 1, atol=1e-5)
    x = prepare_images(frames, (28, 28), "NCHW", IMAGENET_MEAN, IMAGENET_STD)  # [F,3,28,28]
    patches = x.reshape(3, 3, 2, 14, 2, 14)
    ref = np.einsum("fcipjq,dcpq->fijd", patches, wgt)
    ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    assert np.allclose(grid.tokens, ref, atol=1e-4)  # CLS stripped, patch order row-major
    # patch centres in ORIGINAL pixels
    assert np.allclose(grid.patch_centers[0, 0], [15, 10]) and np.allclose(grid.patch_centers[1, 1], [45, 30])


def test_onnx_tokens_sidecar_overrides_patch_size(tmp_path):
    path, _ = _tiny_vit(tmp_path / "vit.onnx", size=28, p=7)
    frames = np.zeros((1, 28, 28, 3), np.uint8)
    (tmp_path / "vit.onnx.json").write_text(json.dumps({"patch_size": 7}))
    assert extract_tokens(frames, "onnx", path, patch_size=14).tokens.shape[1:3] == (4, 4)


def test_onnx_missing_model_names_file(tmp_path):
    with pytest.raises(InputError) as e:
        extract_tokens(np.zeros((1, 8, 8, 3), np.uint8), "onnx", tmp_path / "nope.onnx")
    assert "nope.onnx" in str(e.value)


def _segmenter(path, n=16, person=15):
    wgt = np.zeros((3, 21), np.float32)
    wgt[0, person] = 10.0  # person score = 10 * R (R scaled to [-1, 1])
    wgt[0, 0] = -10.0  # background score = -10 * R
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["sub_7", "w"], ["scores"])], "seg",
        [helper.make_tensor_value_info("sub_7", TensorProto.FLOAT, [1, n, n, 3])],
        [helper.make_tensor_value_info("scores", TensorProto.FLOAT, [1, n, n, 21])],
        [numpy_helper.from_array(wgt, "w")])
    return _save(graph, path)


def test_onnx_segmenter_nhwc_foreground(tmp_path):
    path = _segmenter(tmp_path / "seg.onnx")
    frames = np.zeros((2, 32, 48, 3), np.uint8)
    frames[:, :, :24, 0] = 255  # red left half -> person
    m = dynamic_mask(frames, None, None, backend="onnx", model_path=path)
    assert m.shape == (2, 32, 48) and m.dtype == np.float32
    assert m[:, :, :18].min() > 0.95 and m[:, :, 30:].max() < 0.05
    # class list: asking only for class 3 gives ~0 everywhere
    m3 = dynamic_mask(frames, None, None, backend="onnx", model_path=path, foreground_classes=[3])
    assert m3.max() < 0.05


def _depth_model(path, n=32):
    graph = helper.make_graph(
        [helper.make_node("ReduceMean", ["img", "axes"], ["inv"], keepdims=1)], "depth",
        [helper.make_tensor_value_info("img", TensorProto.FLOAT, [1, 3, n, n])],
        [helper.make_tensor_value_info("inv", TensorProto.FLOAT, [1, 1, n, n])],
        [numpy_helper.from_array(np.array([1], np.int64), "axes")])
    return _save(graph, path)


def test_onnx_depth_inverse_aligned_robustly(tmp_path):
    path = _depth_model(tmp_path / "depth.onnx")
    H, W, F = 48, 64, 2
    ys = np.linspace(0, 1, H)[:, None] * np.ones((1, W))
    gt = (2.0 + 3.0 * ys).astype(np.float32)  # depth 2..5
    inv = 1.0 / gt
    gray = (inv - inv.min()) / (inv.max() - inv.min()) * 200 + 20  # model output is affine in this
    frames = np.repeat(np.repeat(gray[None, ..., None], 3, -1), F, 0).astype(np.uint8)
    rng = np.random.default_rng(0)
    anchors = []
    for _ in range(F):
        u, v = rng.uniform(0, W, 60), rng.uniform(0, H, 60)
        d = gt[v.astype(int), u.astype(int)].copy()
        d[:8] *= 3.0  # outliers
        anchors.append(np.stack([u, v, d], 1))
    K = np.tile(np.eye(3), (F, 1, 1)); w2c = np.tile(np.eye(4), (F, 1, 1))
    depth, conf = estimate_depth(frames, K, w2c, backend="onnx", model_path=path, anchors=anchors)
    assert depth.shape == (F, H, W)
    absrel = np.abs(depth - gt) / gt
    assert np.median(absrel) < 0.03 and absrel.mean() < 0.06


def test_real_dinov2(shared_dir):
    path = shared_dir / "models" / "dinov2_vits14_224.onnx"
    if not path.is_file():
        pytest.skip("dinov2 model absent")
    frames = np.random.default_rng(0).integers(0, 255, (2, 120, 160, 3), dtype=np.uint8)
    grid = extract_tokens(frames, "onnx", path)
    assert grid.tokens.shape == (2, 16, 16, 384)
    assert np.allclose(np.linalg.norm(grid.tokens, axis=-1), 1, atol=1e-4)
    assert np.allclose(grid.patch_centers[0, 0], [5, 3.75])


def test_real_deeplab(shared_dir):
    path = shared_dir / "models" / "deeplabv3_mobilenet_pascal21_257.onnx"
    if not path.is_file():
        pytest.skip("deeplab model absent")
    frames = np.full((1, 100, 120, 3), 127, np.uint8)
    m = dynamic_mask(frames, None, None, backend="onnx", model_path=path)
    assert m.shape == (1, 100, 120) and 0 <= m.min() and m.max() <= 1
    assert m.mean() < 0.5  # a flat grey image is background


def _static_tracker(path):
    """Tracker that says every query stays where it is and is visible (tests the I/O contract)."""
    c = lambda name, v: numpy_helper.from_array(np.asarray(v, np.int64), name)  # noqa: E731
    nodes = [
        helper.make_node("Slice", ["queries", "one", "three", "one"], ["q2"]),
        helper.make_node("Unsqueeze", ["q2", "one"], ["q3"]),
        helper.make_node("Shape", ["queries"], ["qs"]),
        helper.make_node("Slice", ["qs", "zero", "one", "zero"], ["P"]),
        helper.make_node("Shape", ["frames"], ["fs"]),
        helper.make_node("Slice", ["fs", "zero", "one", "zero"], ["F"]),
        helper.make_node("Concat", ["P", "F", "two"], ["tshape"], axis=0),
        helper.make_node("Expand", ["q3", "tshape"], ["xy"]),
        helper.make_node("ReduceSum", ["xy", "two"], ["s"], keepdims=0),
        helper.make_node("Mul", ["s", "zerof"], ["s0"]),
        helper.make_node("Add", ["s0", "onef"], ["visible"]),
    ]
    graph = helper.make_graph(
        nodes, "tracker",
        [helper.make_tensor_value_info("frames", TensorProto.FLOAT, ["F", 3, "H", "W"]),
         helper.make_tensor_value_info("queries", TensorProto.FLOAT, ["P", 3])],
        [helper.make_tensor_value_info("xy", TensorProto.FLOAT, ["P", "F", 2]),
         helper.make_tensor_value_info("visible", TensorProto.FLOAT, ["P", "F"])],
        [c("zero", [0]), c("one", [1]), c("two", [2]), c("three", [3]),
         numpy_helper.from_array(np.array(0, np.float32), "zerof"), numpy_helper.from_array(np.array(1, np.float32), "onef")])
    return _save(graph, path)


def test_onnx_tracker_contract(tmp_path):
    from engine.priors import track_points

    path = _static_tracker(tmp_path / "trk.onnx")
    frames = np.zeros((4, 30, 40, 3), np.uint8)
    tr = track_points(frames, num_points=12, backend="onnx", model_path=path)
    P = tr.xy.shape[0]
    assert tr.xy.shape == (P, 4, 2) and P >= 12 and tr.visible.all()
    assert np.allclose(tr.xy[:, 0], tr.xy[:, 3]) and (tr.xy[..., 0] < 40).all() and (tr.xy[..., 1] < 30).all()
    assert np.allclose(tr.confidence, 1 / (1 + np.exp(-1)))


def test_onnx_segmenter_nchw_class_first(tmp_path):
    n = 20
    w = np.zeros((21, 3, 1, 1), np.float32)
    w[7, 1] = 20.0  # class 7 score = 20 * normalised G; background = 0
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w"], ["scores"])], "seg",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, n, n])],
        [helper.make_tensor_value_info("scores", TensorProto.FLOAT, [1, 21, n, n])],
        [numpy_helper.from_array(w, "w")])
    path = _save(graph, tmp_path / "seg_nchw.onnx")
    frames = np.zeros((1, 40, 40, 3), np.uint8)
    frames[:, 20:, :, 1] = 255  # green bottom half -> class 7 (ImageNet-normalised G ~ +2.4)
    m = dynamic_mask(frames, None, None, backend="onnx", model_path=path, foreground_classes=[7])
    assert m[0, 28:].min() > 0.95 and m[0, :12].max() < 0.05
