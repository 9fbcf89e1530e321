"""The whole engine from the command line on a Blender-generated vrig scene."""

import json
import os
import subprocess
import sys

import pytest

from engine import bundle as B
from engine.protocol import parse_event

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    pytest.importorskip("bpy")
    sys.path.insert(0, REPO)
    from tools.synth_scene import generate_scene

    return generate_scene(tmp_path_factory.mktemp("synth") / "scene", preset="tiny", seed=0)


def _engine(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "engine", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow
def test_train_command_end_to_end(synth_scene, tmp_path):
    """``engine train`` then ``engine eval --split train`` from the command line, with the
    scene's ground-truth motion mask as ``--mask-path`` (the tiny scene's weight-free mask
    misses its moving parts; depth and tracks stay weight-free). Full-frame PSNR cannot see
    the moving cube, arm and flag (a few % of the image), so the claims are about them: inside
    the ground-truth moving masks the renders beat the still plate (the training frames'
    median, what a model that lost the motion scores), and what moves in the bundle (the
    Gaussians bound to nodes whose trajectories move) covers the moving objects at three
    times. (The model before the static / dynamic split, ``{"split": false, "motion_init":
    "rest"}``, moves nearly every node, so its moving silhouette is the whole view: IoU 0.11-0.13.)"""
    import numpy as np
    import torch

    from engine.bench.oracle import write_oracle_priors
    from engine.bench.still_plate import bundle_split_frames, still_plate_scores
    from engine.train.from_bundle import model_from_bundle

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from test_moving_objects import silhouette_iou

    out = tmp_path / "run"
    mask = write_oracle_priors(synth_scene, tmp_path / "oracle", ["mask"])["mask_path"]
    res = _engine("train", synth_scene, "--out", out, "--steps", "300", "--mask-path", mask, "--jsonl")
    assert res.returncode == 0, res.stderr[-3000:]
    events = [parse_event(line) for line in res.stdout.splitlines()]
    assert all(events), "every stdout line is a protocol event"
    stages = {e["stage"] for e in events if e["event"] == "progress"}
    assert {"tracks", "depth", "nodes", "train"} <= stages
    result = events[-1]
    assert result["event"] == "result"
    # held-out views (a rigidly offset camera that also sees parts the training camera never saw)
    assert result["eval"]["ssim"] > result["eval_init"]["ssim"] + 0.1, result
    bundle = B.load_bundle(out)
    assert bundle.nodes.count == result["nodes"] and bundle.gaussians.count == result["gaussians"]
    assert {c["split"] for c in bundle.scene["cameras"]} == {"train", "val"}

    # the moving objects in the training views: masked PSNR beats the still plate by 3 dB
    # (measured +3.92-4.06 dB over seeds 0-2; the model before the split +3.67-3.70: this claim alone
    # does not tell them apart, the silhouette below does)
    res = _engine("eval", out, "--split", "train", "--json")
    assert res.returncode == 0, res.stderr[-3000:]
    ev = json.loads(res.stdout.splitlines()[-1])
    frames, masks = bundle_split_frames(out, "train")
    plate = still_plate_scores(frames, masks)
    assert ev["mean"]["frames"] == len(frames) == 12
    assert ev["mean"]["masked_psnr"] > plate["plate_masked_psnr"] + 3.0, (ev["mean"], plate)

    # what moves in the bundle is what moves in the footage: the Gaussians bound (by most of
    # their weight) to nodes whose trajectories move render a silhouette with IoU >= 0.6 against
    # the ground-truth mask at three times (measured 0.72-0.89 over seeds 0-2; before the split 0.11-0.13,
    # with 92% of its nodes moving)
    model = model_from_bundle(bundle)
    cams = [c for c in bundle.scene["cameras"] if c["split"] == "train"]
    with torch.no_grad():
        pos, _ = model.node_states([c["time"] for c in cams])  # [N, T, 3]
    node_moves = (pos - pos[:, :1]).abs().amax(dim=(1, 2)) > 1e-3
    assert 0 < int(node_moves.sum()) < 0.5 * len(node_moves), int(node_moves.sum())  # the room stands still
    moving = (model.bind_w * node_moves[model.bind_idx]).sum(-1) > 0.5 * model.bind_w.sum(-1)
    order = np.argsort([c["time"] for c in cams])
    ious = [silhouette_iou(model, moving, cams[k]["time"], cams[k]["K"], cams[k]["w2c"], cams[k]["width"],
                           cams[k]["height"], masks[k]) for k in (order[1], order[len(order) // 2], order[-2])]
    assert min(ious) >= 0.6, ious


def test_init_command_writes_nodes_only(synth_scene, tmp_path):
    out = tmp_path / "init"
    res = _engine("init", synth_scene, "--out", out, "--nodes", "64", "--jsonl")
    assert res.returncode == 0, res.stderr[-3000:]
    result = parse_event(res.stdout.splitlines()[-1])
    assert result["nodes"] <= 64
    bundle = B.load_bundle(out)
    assert bundle.gaussians is None and bundle.nodes.count == result["nodes"]
    assert bundle.nodes.p_dyn is not None


@pytest.mark.slow
def test_motion_init_auto_lifts_tracks_and_rest_overrides(synth_scene, tmp_path):
    """``auto`` starts every node on its lifted tracks (the paper's initialisation), with
    the weight-free depth made constant along moving tracks and with ground-truth depth
    alike; the bundle's config records which ran; ``--motion-init rest`` overrides it.
    (Nodes that start at rest on an object crossing the frame never find it again: the
    object went missing, docs/benchmarks.md "Moving objects".)"""
    import numpy as np

    from engine.bench.oracle import write_oracle_priors

    def init(*extra):
        out = tmp_path / f"init{len(list(tmp_path.iterdir()))}"
        res = _engine("init", synth_scene, "--out", out, "--nodes", "64", "--cache", tmp_path / "cache", "--jsonl",
                      *extra)
        assert res.returncode == 0, res.stderr[-3000:]
        bundle = B.load_bundle(out)
        n = bundle.nodes
        motion = np.abs(n.pos_keys - n.pos_keys[:, :1]).max()
        return bundle.scene["config"]["motion_init"], motion, n

    # ground-truth mask (the tiny scene's weight-free mask misses its moving parts, which
    # would freeze every track)
    paths = write_oracle_priors(synth_scene, tmp_path / "oracle", ["depth", "mask"])
    mode, motion, _ = init("--mask-path", paths["mask_path"])  # weight-free depth
    assert mode == "tracks" and motion > 1e-3  # the tiny scene's cube and arm move
    gt = ("--depth-path", paths["depth_path"], "--mask-path", paths["mask_path"])
    mode, motion, _ = init(*gt)
    assert mode == "tracks" and motion > 1e-3
    mode, motion, nodes = init(*gt, "--motion-init", "rest")
    assert mode == "rest" and motion == 0.0
    assert np.allclose(nodes.pos_keys, nodes.centers[:, None], atol=1e-6)


@pytest.mark.parametrize("args,needle", [
    (["train", "/nonexistent/clip", "--out", "X"], "does not exist"),
    (["train", "CLIP", "--out", "X", "--config", "BADCFG"], "unknown config key"),
])
def test_bad_input_is_one_clear_line(synth_scene, tmp_path, args, needle):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"stepz": 3}))
    args = [str(synth_scene) if a == "CLIP" else str(tmp_path / "o") if a == "X" else str(cfg) if a == "BADCFG"
            else a for a in args]
    res = _engine(*args)
    assert res.returncode == 2
    assert needle in res.stderr and "Traceback" not in res.stderr
