"""Flow sources (DIS / RAFT-contract ONNX), learned flow shared by tracks and the motion mask,
dense re-seeding on moving parts; tiny ONNX models built by the test, the real RAFT-small
from ``../shared/models`` when present."""

from __future__ import annotations

import sys
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

sys.path.insert(0, str(Path(__file__).parent))
import test_priors_scene as scene  # noqa: E402

from engine.errors import InputError  # noqa: E402
from engine.priors import PriorConfig, compute_priors, track_points  # noqa: E402
from engine.priors import flow as flow_mod  # noqa: E402

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "models"
RAFT = SHARED / "raft_small_it6.onnx"


def _save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return str(path)


def _tiny_raft(path, gain=0.1, names=("image1", "image2")):
    """RAFT contract: flow = gain * 8x8-block mean of (image2 - image1)[:, :2], upsampled x8.

    Only valid for H, W multiples of 8 (else the block grid is smaller than the input and
    the output cannot be cropped back): checks the padding. Antisymmetric, so the
    forward-backward check passes."""
    nodes = [
        helper.make_node("Sub", [names[1], names[0]], ["d"]),
        helper.make_node("Slice", ["d", "s0", "s1", "ax"], ["d2"]),
        helper.make_node("AveragePool", ["d2"], ["p"], kernel_shape=[8, 8], strides=[8, 8]),
        helper.make_node("Resize", ["p", "", "sc"], ["u"], mode="nearest"),
        helper.make_node("Mul", ["u", "g"], ["flow"]),
        helper.make_node("Identity", ["p"], ["flow_low"]),
    ]
    graph = helper.make_graph(
        nodes, "raft",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, 3, "H", "W"]) for n in names],
        [helper.make_tensor_value_info("flow", TensorProto.FLOAT, [1, 2, "H", "W"]),
         helper.make_tensor_value_info("flow_low", TensorProto.FLOAT, [1, 2, "h", "w"])],
        [numpy_helper.from_array(np.array([0], np.int64), "s0"), numpy_helper.from_array(np.array([2], np.int64), "s1"),
         numpy_helper.from_array(np.array([1], np.int64), "ax"),
         numpy_helper.from_array(np.array([1, 1, 8, 8], np.float32), "sc"),
         numpy_helper.from_array(np.array(gain, np.float32), "g")])
    return _save(graph, path)


def _drifting_frames(F=4, H=60, W=90, step=10):
    """Textured frames whose R and G channels brighten by ``step`` per frame: the tiny model
    reads that as a flow of ``gain * step`` px per frame in x and y."""
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.random((H, W, 3)).astype(np.float32), (0, 0), 2)
    base = (base - base.min()) / (base.max() - base.min()) * 150 + 20
    out = np.repeat(base[None], F, 0)
    out[..., :2] += step * np.arange(F)[:, None, None, None]
    return np.clip(out, 0, 255).astype(np.uint8)


def test_raft_contract_pads_crops_and_memoises(tmp_path):
    model = _tiny_raft(tmp_path / "raft.onnx")
    frames = _drifting_frames(H=60, W=90)  # neither a multiple of 8
    src = flow_mod.FlowSource(frames, "onnx", model, max_width=90)
    assert src.size == (60, 90)
    fl = src(0, 2)
    assert fl.shape == (60, 90, 2) and fl.dtype == np.float32
    assert np.allclose(np.median(fl[:56, :88].reshape(-1, 2), 0), [2.0, 2.0], atol=0.05)  # 0.1 * 20
    assert np.allclose(np.median(src(2, 0).reshape(-1, 2), 0), [-2.0, -2.0], atol=0.05)
    with mock.patch.object(flow_mod, "raft_flow", side_effect=AssertionError("recomputed")):
        src(0, 2)  # memoised
    half = src.resampled(0, 2, (30, 45))
    assert half.shape == (30, 45, 2) and np.allclose(np.median(half.reshape(-1, 2), 0), [1.0, 1.0], atol=0.05)


def test_flow_model_with_wrong_inputs_is_one_clear_error(tmp_path):
    model = _tiny_raft(tmp_path / "other.onnx", names=("a", "b"))
    with pytest.raises(InputError) as e:
        flow_mod.FlowSource(_drifting_frames(), "onnx", model)
    assert "other.onnx" in str(e.value) and "image1" in str(e.value)


def test_resolve_flow_backend(tmp_path, monkeypatch):
    monkeypatch.setattr(flow_mod, "MODELS_DIR", tmp_path)
    assert flow_mod.resolve_flow_backend("auto", None) == ("dis", None)
    assert flow_mod.resolve_flow_backend("dis", None) == ("dis", None)
    with pytest.raises(InputError):
        flow_mod.resolve_flow_backend("onnx", None)
    with pytest.raises(InputError):
        flow_mod.resolve_flow_backend("raft", None)
    (tmp_path / flow_mod.SHIPPED_FLOW).write_bytes(b"x")
    assert flow_mod.resolve_flow_backend("auto", None) == ("onnx", str(tmp_path / flow_mod.SHIPPED_FLOW))
    assert flow_mod.resolve_flow_backend("auto", "m.onnx") == ("onnx", "m.onnx")


def test_tracks_follow_learned_flow(tmp_path):
    model = _tiny_raft(tmp_path / "raft.onnx")
    frames = _drifting_frames(F=4, H=64, W=96)
    src = flow_mod.FlowSource(frames, "onnx", model, max_width=96)
    tr = track_points(frames, num_points=200, source=src, dense_moving=False)
    sel = (tr.query_frame == 0) & tr.visible.all(1)
    assert sel.sum() > 50
    steps = np.diff(tr.xy[sel], axis=1)  # 0.1 * 10 px per frame in x and y
    assert np.allclose(steps, 1.0, atol=1e-3)


def test_compute_priors_computes_each_learned_flow_once(tmp_path):
    model = _tiny_raft(tmp_path / "raft.onnx")
    frames = _drifting_frames(F=4, H=64, W=96)
    K = np.tile(np.array([[90.0, 0, 48], [0, 90, 32], [0, 0, 1]]), (4, 1, 1))
    w2c = np.tile(np.eye(4), (4, 1, 1)); w2c[:, 0, 3] = -0.05 * np.arange(4)
    cfg = PriorConfig(num_points=150, flow_backend="onnx", flow_model=model, flow_model_width=96)
    calls = []
    real = flow_mod.raft_flow
    with mock.patch.object(flow_mod, "raft_flow", side_effect=lambda *a: calls.append(1) or real(*a)):
        p = compute_priors(frames, K, w2c, cfg, cache_dir=tmp_path / "c")
    assert p.dynamic.shape == (4, 64, 96) and p.tracks.xy.shape[1] == 4
    assert len(calls) == 2 * 3  # tracks and the motion mask share the forward/backward pairs
    dis = compute_priors(frames, K, w2c, PriorConfig(num_points=150), cache_dir=tmp_path / "c")
    assert dis.keys["tracks"] != p.keys["tracks"] and dis.keys["dynamic"] != p.keys["dynamic"]
    assert dis.keys["tokens"] == p.keys["tokens"]


def test_dense_reseeding_puts_more_tracks_on_the_moving_square():
    frames, depth, mask, K, w2c = scene.render()
    counts = []
    for dense in (False, True):
        tr = track_points(frames, num_points=300, dense_moving=dense)
        f0 = tr.query_frame
        u = np.clip(tr.xy[np.arange(len(f0)), f0, 0].astype(int), 0, scene.W - 1)
        v = np.clip(tr.xy[np.arange(len(f0)), f0, 1].astype(int), 0, scene.H - 1)
        counts.append(int((mask[f0, v, u] & (f0 > 0)).sum()))
    assert counts[1] >= 2 * counts[0] > 0, counts


CUPS = SHARED.parent / "data" / "clips" / "cups.mp4"


@pytest.mark.skipif(not (RAFT.is_file() and CUPS.is_file()), reason="../shared RAFT-small / cups.mp4 not present")
def test_real_raft_recovers_a_translation():
    # a real photograph: RAFT-small is trained on natural images (on i.i.d. noise texture it is
    # off by ~0.25 px, see docs/benchmarks.md: it also loses to DIS on the generated scenes)
    cap = cv2.VideoCapture(str(CUPS))
    ok, bgr = cap.read()
    cap.release()
    assert ok
    img = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), (260, 146), interpolation=cv2.INTER_AREA)
    M = np.float32([[1, 0, 3.0], [0, 1, -1.5]])
    b = cv2.warpAffine(img, M, (260, 146), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    frames = np.stack([img, b])[:, 20:126, 20:230]  # 106 x 210: padded to /8 inside
    # contract check (units, direction, padding): a wrong scale or sign is off by >= 1.5 px;
    # RAFT-small itself is off by up to ~0.2 px on the texture-less table
    src = flow_mod.FlowSource(frames, "onnx", str(RAFT), max_width=210)
    assert np.allclose(np.median(src(0, 1)[10:-10, 10:-10].reshape(-1, 2), 0), [3.0, -1.5], atol=0.25)
    assert np.allclose(np.median(src(1, 0)[10:-10, 10:-10].reshape(-1, 2), 0), [-3.0, 1.5], atol=0.25)


def test_fused_dis_follows_a_small_fast_object():
    # at 160 px the medium preset's half-resolution patches straddle the square's border and
    # drag it towards the background; the finest-scale flow, fused by forward-backward error,
    # follows it without losing the background
    frames, depth, mask, K, w2c = scene.render()
    m = cv2.erode(mask[2].astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    bg = cv2.dilate(mask[2].astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
    gt = np.zeros(mask[2].shape + (2,), np.float32)
    gt[m] = [scene.FX * (scene.SQ_VEL[0] - scene.CAM_STEP) / scene.Z_SQ, scene.FX * scene.SQ_VEL[1] / scene.Z_SQ]
    gt[bg] = [-scene.FX * scene.CAM_STEP / scene.Z_BG, 0.0]
    err = {}
    for fine in (False, True):
        src = flow_mod.FlowSource(frames, "dis", None, max_width=480, fuse_fine=fine)
        e = np.linalg.norm(src(2, 3) - gt, axis=-1)
        err[fine] = (np.median(e[m]), np.median(e[bg]))
        assert np.allclose(src(3, 2)[bg].mean(0), -gt[bg].mean(0), atol=0.1)  # backward flow memoised too
    assert err[False][0] > 0.3 and err[True][0] < 0.15, err
    assert err[True][1] < 0.1, err


def test_default_tracks_use_the_fused_flow(tmp_path):
    frames, depth, mask, K, w2c = scene.render(F=4)
    real = flow_mod.dis_fused
    for fine, expect in ((True, 3), (False, 0)):
        calls = []
        with mock.patch.object(flow_mod, "dis_fused", side_effect=lambda *a: calls.append(1) or real(*a)):
            p = compute_priors(frames, K[:4], w2c[:4], PriorConfig(num_points=200, flow_fine=fine))
        assert len(calls) == expect and p.tracks.xy.shape[1] == 4  # one call per pair gives both directions
    assert PriorConfig().flow_fine


def test_the_motion_mask_shares_the_trackers_flow(tmp_path):
    # with the fine-scale fused DIS the motion mask resamples the tracker's memoised flows; without
    # it the mask computes its own plain DIS
    frames, depth, mask, K, w2c = scene.render(F=4)
    real = flow_mod.dis_flow
    plain = {}
    for fine in (True, False):
        calls = []
        with mock.patch.object(flow_mod, "dis_flow", side_effect=lambda *a: calls.append(1) or real(*a)):
            p = compute_priors(frames, K[:4], w2c[:4], PriorConfig(num_points=200, flow_fine=fine))
        plain[fine] = len(calls)
        assert p.dynamic.shape == frames.shape[:3]
    assert plain[True] == 0 and plain[False] > 0, plain


def test_cli_flow_and_depth_output_options(tmp_path):
    import argparse

    from engine.commands._train_options import add_clip_options, prior_config_from_args

    parser = argparse.ArgumentParser()
    add_clip_options(parser)
    base = [str(tmp_path / "clip.mp4"), "--out", str(tmp_path / "out"), "--no-models"]
    cfg = prior_config_from_args(parser.parse_args(base + ["--flow-model", "m.onnx", "--depth-output", "depth"]))
    assert (cfg.flow_backend, cfg.flow_model, cfg.depth_output) == ("onnx", "m.onnx", "depth")
    cfg = prior_config_from_args(parser.parse_args(base + ["--flow-backend", "auto"]))
    assert (cfg.flow_backend, cfg.flow_model, cfg.depth_output) == ("auto", None, None)
    assert prior_config_from_args(parser.parse_args(base)).flow_backend == "dis"
    assert cfg.flow_fuse_dis and not prior_config_from_args(parser.parse_args(base + ["--flow-alone"])).flow_fuse_dis


class _StubFlow:
    """A flow source returning fixed flows (``flows[(f, g)]``) at ``size``."""

    def __init__(self, flows, size, gray=None, model_path=None):
        self.flows, self.size, self.gray, self.model_path = flows, size, gray, model_path
        self.scale = 1.0

    def __call__(self, f, g):
        return self.flows[(f, g)]

    def resampled(self, f, g, size):
        return flow_mod.resize_flow(self(f, g), size)

    def forget(self, f, g):
        pass


def _translated_pair(shift=(3.0, -1.5), H=96, W=128):
    rng = np.random.default_rng(1)
    a = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 1.5)
    a = ((a - a.min()) / (a.max() - a.min()) * 200 + 20).astype(np.uint8)
    # b(p + shift) = a(p): the flow a -> b is ``shift`` everywhere
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    b = cv2.warpAffine(a, M, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.stack([a, b]), np.array(shift, np.float32)


def test_fused_source_takes_per_pixel_the_flow_that_matches_the_image():
    gray, shift = _translated_pair()
    H, W = gray.shape[1:]
    left = np.zeros((H, W), bool); left[:, : W // 2] = True
    dis_fl = np.where(left[..., None], 0.0, shift).astype(np.float32)  # DIS right on the right half only
    half = np.where(left[::2, ::2, None], shift / 2, 0.0).astype(np.float32)  # learned, at half size: left only
    dis = _StubFlow({(0, 1): dis_fl}, (H, W), gray)
    learned = _StubFlow({(0, 1): half}, (H // 2, W // 2), model_path="m.onnx")
    fused = flow_mod.FusedFlowSource(dis, learned)
    out = fused(0, 1)
    assert out.shape == (H, W, 2) and fused.size == (H, W) and fused.gray is gray
    inner = np.zeros((H, W), bool); inner[6:-6, 6:-6] = True
    inner[:, W // 2 - 5: W // 2 + 5] = False  # the residual's 5-px window straddles the seam
    err = np.linalg.norm(out - shift, axis=-1)
    assert np.median(err[inner]) < 1e-6 and np.mean(err[inner] < 1e-3) > 0.98, np.mean(err[inner] < 1e-3)
    assert 0.4 < fused.picked < 0.6
    assert fused.resampled(0, 1, (H // 2, W // 2)).shape == (H // 2, W // 2, 2)
    # the same wrong flow on both sides: whichever is taken, nothing better appears
    fused_bad = flow_mod.FusedFlowSource(_StubFlow({(0, 1): np.zeros((H, W, 2), np.float32)}, (H, W), gray), learned)
    assert np.mean(np.linalg.norm(fused_bad(0, 1) - shift, axis=-1)[inner] < 1e-3) < 0.55


def test_photometric_residual_is_zero_for_the_true_flow_only():
    gray, shift = _translated_pair()
    true = np.broadcast_to(shift, gray.shape[1:] + (2,)).astype(np.float32)
    r_true = flow_mod.photometric_residual(gray[0], gray[1], true)[8:-8, 8:-8]
    r_off = flow_mod.photometric_residual(gray[0], gray[1], true + np.float32([0.5, 0.0]))[8:-8, 8:-8]
    assert np.median(r_true) < 1.0 < np.median(r_off)


def test_a_learned_flow_that_misreads_the_image_loses_to_dis(tmp_path):
    # the tiny model reads the frames' brightening as 1 px a frame of motion; the texture does
    # not move, so DIS's zero flow matches the image better and the fused tracks stand still
    model = _tiny_raft(tmp_path / "raft.onnx")
    frames = _drifting_frames(F=4, H=64, W=96)
    K = np.tile(np.array([[90.0, 0, 48], [0, 90, 32], [0, 0, 1]]), (4, 1, 1))
    w2c = np.tile(np.eye(4), (4, 1, 1))
    steps = {}
    for fuse in (True, False):
        cfg = PriorConfig(num_points=150, flow_backend="onnx", flow_model=model, flow_model_width=96,
                          flow_fuse_dis=fuse)
        p = compute_priors(frames, K, w2c, cfg, cache_dir=tmp_path / "c")
        sel = (p.tracks.query_frame == 0) & p.tracks.visible.all(1)
        assert sel.sum() > 50
        steps[fuse] = np.median(np.abs(np.diff(p.tracks.xy[sel], axis=1)))
    assert steps[False] > 0.9 and steps[True] < 0.1, steps
