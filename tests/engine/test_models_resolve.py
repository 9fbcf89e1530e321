"""Backend ``auto``: installed models fill the priors the user left open; scene.json and the
report record which model (name + SHA-256) or weight-free backend produced each prior."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from engine.models import ModelSpec, ModelStore, describe_priors, fetch, resolve_prior_models
from engine.priors import PriorConfig
from tests.engine._model_server import ModelServer, tiny_onnx_bytes

REPO = Path(__file__).resolve().parents[2]


def _install(store: ModelStore, spec: ModelSpec, data: bytes) -> Path:
    """Install through the real fetch path, from a local server."""
    with ModelServer() as srv:
        fetch(dataclasses.replace(spec, urls=(srv.add("/m.onnx", data),)), store)
    return store.model_path(spec)


def _depth_spec(data: bytes, name="tiny-depth") -> ModelSpec:
    return ModelSpec(name=name, role="depth", title="t", file=f"{name}.onnx", license="MIT",
                     sha256=hashlib.sha256(data).hexdigest(), bytes=len(data))


def test_nothing_installed_keeps_weight_free(tmp_path):
    cfg = PriorConfig()
    out = resolve_prior_models(cfg, ModelStore(tmp_path), registry=())
    assert out == cfg
    desc = describe_priors(out, ModelStore(tmp_path), registry=())
    assert desc["depth"] == {"backend": "sparse"} and desc["tokens"] == {"backend": "handcrafted"}
    assert desc["mask"] == {"backend": "motion"} and desc["tracks"] == {"backend": "flow"}


def test_installed_model_fills_open_roles_only(tmp_path):
    data = tiny_onnx_bytes()
    spec = _depth_spec(data)
    store = ModelStore(tmp_path / "models")
    path = _install(store, spec, data)
    reg = (spec,)
    out = resolve_prior_models(PriorConfig(), store, reg)
    assert (out.depth_backend, out.depth_model) == ("onnx", str(path))
    assert out.tokens_backend == "handcrafted" and out.tokens_model is None
    desc = describe_priors(out, store, reg)
    assert desc["depth"]["model"] == "tiny-depth" and desc["depth"]["sha256"] == spec.sha256
    # a user choice wins: explicit model, precomputed file
    mine = tmp_path / "mine.onnx"
    mine.write_bytes(tiny_onnx_bytes(seed=3))
    explicit = PriorConfig(depth_backend="onnx", depth_model=str(mine))
    assert resolve_prior_models(explicit, store, reg) == explicit
    d = describe_priors(explicit, store, reg)["depth"]
    assert d["model"] == "mine" and d["sha256"] == hashlib.sha256(mine.read_bytes()).hexdigest()
    pre = PriorConfig(depth_path=str(tmp_path / "depth.npy"))
    assert resolve_prior_models(pre, store, reg) == pre
    assert describe_priors(pre, store, reg)["depth"] == {"backend": "file", "file": str(tmp_path / "depth.npy")}


def test_model_changed_after_install_is_not_used(tmp_path):
    data = tiny_onnx_bytes()
    spec = _depth_spec(data)
    store = ModelStore(tmp_path / "models")
    path = _install(store, spec, data)
    path.write_bytes(data + b"x")
    assert store.state(spec).status == "changed"
    assert resolve_prior_models(PriorConfig(), store, (spec,)).depth_backend == "sparse"
    assert store.verify(spec)["status"] == "mismatch"


def test_a_file_matching_a_registry_hash_is_named_by_it(tmp_path):
    data = tiny_onnx_bytes()
    spec = _depth_spec(data)
    elsewhere = tmp_path / "renamed.onnx"
    elsewhere.write_bytes(data)
    cfg = PriorConfig(depth_backend="onnx", depth_model=str(elsewhere))
    assert describe_priors(cfg, ModelStore(tmp_path / "m"), (spec,))["depth"]["model"] == "tiny-depth"


@dataclasses.dataclass
class _FlowConfig:  # a PriorConfig with a learned-flow role whose default is "auto"
    flow_backend: str = "auto"
    flow_model: str | None = None


def test_auto_flow_takes_cached_then_shipped_model(tmp_path, monkeypatch):
    data = tiny_onnx_bytes(seed=5)
    shipped_dir = tmp_path / "engine"
    (shipped_dir / "priors" / "models").mkdir(parents=True)
    (shipped_dir / "priors" / "models" / "flow.onnx").write_bytes(data)
    import engine.models.registry as R

    monkeypatch.setattr(R, "ENGINE_ROOT", shipped_dir)
    spec = ModelSpec(name="tiny-flow", role="flow", title="t", file="flow.onnx", license="BSD-3-Clause",
                     shipped="priors/models/flow.onnx", sha256=hashlib.sha256(data).hexdigest())
    store = ModelStore(tmp_path / "models")
    out = resolve_prior_models(_FlowConfig(), store, (spec,))
    assert out.flow_model == str(shipped_dir / "priors/models/flow.onnx") and out.flow_backend == "onnx"
    assert describe_priors(out, store, (spec,))["flow"]["model"] == "tiny-flow"
    # "models fetch" of a shipped model copies it into the cache (no network); auto then uses the cache
    info = fetch(spec, store)
    assert info["source"].endswith("flow.onnx") and store.state(spec).status == "installed"
    assert resolve_prior_models(_FlowConfig(), store, (spec,)).flow_model == str(store.model_path(spec))
    # an explicit weight-free choice is respected
    assert resolve_prior_models(_FlowConfig(flow_backend="dis"), store, (spec,)).flow_backend == "dis"


def _args(**kw):
    base = dict(tokens_model=None, depth_model=None, mask_model=None, tracks_model=None, depth_path=None,
                mask_path=None, tracks_path=None, no_models=False, flow_backend=None, flow_model=None,
                clip=str(Path(__file__)))  # not a clip manifest: no manifest priors
    return argparse.Namespace(**{**base, **kw})


def test_cli_options_resolve_unless_no_models(tmp_path, monkeypatch):
    from engine.commands._train_options import prior_config_from_args

    data = tiny_onnx_bytes()
    reg = tmp_path / "reg.json"
    reg.write_text(json.dumps({"models": [{"name": "tiny-depth", "role": "depth", "title": "t",
                                           "file": "tiny-depth.onnx", "license": "MIT",
                                           "sha256": hashlib.sha256(data).hexdigest()}]}))
    monkeypatch.setenv("MOTION_SPLATS_REGISTRY", str(reg))
    monkeypatch.setenv("MOTION_SPLATS_MODELS", str(tmp_path / "models"))
    assert prior_config_from_args(_args()).depth_backend == "sparse"
    _install(ModelStore(), _depth_spec(data), data)
    assert prior_config_from_args(_args()).depth_backend == "onnx"
    assert prior_config_from_args(_args(no_models=True)).depth_backend == "sparse"


def test_report_table_rows():
    from engine.report import _prior_rows

    rows = _prior_rows({"depth": {"backend": "onnx", "model": "m", "sha256": "ab", "license": "MIT"},
                        "tokens": {"backend": "handcrafted"}, "mask": {"backend": "file", "file": "/x/masks"}})
    assert rows == [["depth", "onnx", "m", "ab", "MIT"], ["tokens", "handcrafted", "weight-free", "", ""],
                    ["mask", "file", "/x/masks", "", ""]]


@pytest.mark.slow
def test_fetch_then_init_uses_the_model_and_scene_json_says_so(tmp_path):
    """Acceptance: `models fetch NAME` then `init CLIP` with no other flag uses the installed
    depth model; scene.json records its name and SHA-256 and the weight-free backends."""
    pytest.importorskip("bpy")
    sys.path.insert(0, str(REPO))
    from tools.synth_scene import generate_scene

    clip = generate_scene(tmp_path / "scene", preset="tiny", seed=0)
    data = tiny_onnx_bytes()
    sha = hashlib.sha256(data).hexdigest()
    with ModelServer() as srv:
        reg = tmp_path / "reg.json"
        reg.write_text(json.dumps({"models": [{"name": "tiny-depth", "role": "depth", "title": "t",
                                               "file": "tiny-depth.onnx", "license": "MIT", "sha256": sha,
                                               "urls": [srv.add("/d.onnx", data)], "bytes": len(data)}]}))
        env = {**os.environ, "MOTION_SPLATS_REGISTRY": str(reg), "MOTION_SPLATS_MODELS": str(tmp_path / "models")}

        def engine(*args):
            return subprocess.run([sys.executable, "-m", "engine", *map(str, args)], cwd=REPO, env=env,
                                  capture_output=True, text=True, timeout=600)

        res = engine("models", "fetch", "tiny-depth")
        assert res.returncode == 0, res.stderr[-2000:]
    # the tiny model's depth is the frame's brightness, which explains no scene: the depth check
    # would set it aside (tests/engine/test_priors_depth_check.py); this test is about the plumbing
    res = engine("init", clip, "--out", tmp_path / "run", "--nodes", "32", "--depth-check", "off")
    assert res.returncode == 0, res.stderr[-3000:]
    scene = json.loads((tmp_path / "run" / "scene.json").read_text())
    assert scene["priors"]["depth"]["model"] == "tiny-depth" and scene["priors"]["depth"]["sha256"] == sha
    assert scene["priors"]["tokens"] == {"backend": "handcrafted"}
    assert scene["config"]["motion_init"] == "tracks"  # a model depth: tracks are lifted


def test_explicit_flow_backend_beats_an_installed_flow_model(tmp_path, monkeypatch):
    """--flow-backend dis is the default value but a user choice: an installed RAFT must not replace it."""
    from engine.commands._train_options import prior_config_from_args

    data = tiny_onnx_bytes(seed=7)
    reg = tmp_path / "reg.json"
    reg.write_text(json.dumps({"models": [{"name": "tiny-flow", "role": "flow", "title": "t", "file": "f.onnx",
                                           "license": "MIT", "sha256": hashlib.sha256(data).hexdigest()}]}))
    monkeypatch.setenv("MOTION_SPLATS_REGISTRY", str(reg))
    monkeypatch.setenv("MOTION_SPLATS_MODELS", str(tmp_path / "models"))
    spec = ModelSpec(name="tiny-flow", role="flow", title="t", file="f.onnx", license="MIT",
                     sha256=hashlib.sha256(data).hexdigest())
    _install(ModelStore(), spec, data)
    assert prior_config_from_args(_args()).flow_model == str(ModelStore().model_path(spec))
    cfg = prior_config_from_args(_args(flow_backend="dis"))
    assert cfg.flow_backend == "dis" and cfg.flow_model is None


def test_unresolved_auto_flow_is_recorded_as_what_runs(tmp_path):
    """A config whose flow backend is still 'auto' (library use, no resolve) records the model the
    priors will actually run: the shipped RAFT-small by name and hash, else DIS."""
    from engine.models import load_registry
    from engine.priors.flow import shipped_flow_model

    desc = describe_priors(PriorConfig(flow_backend="auto"), ModelStore(tmp_path), load_registry())["flow"]
    if shipped_flow_model() is None:
        assert desc == {"backend": "dis"}
    else:
        raft = next(s for s in load_registry() if s.name == "raft-small")
        assert desc["backend"] == "onnx" and desc["model"] == "raft-small" and desc["sha256"] == raft.sha256


def test_a_learned_flow_is_described_with_its_fusion(tmp_path):
    mine = tmp_path / "flow.onnx"
    mine.write_bytes(tiny_onnx_bytes(seed=5))
    store = ModelStore(tmp_path / "models")
    fused = describe_priors(PriorConfig(flow_backend="onnx", flow_model=str(mine)), store, ())["flow"]
    assert fused["model"] == "flow" and fused["fused_with"] == "dis"
    alone = describe_priors(PriorConfig(flow_backend="onnx", flow_model=str(mine), flow_fuse_dis=False), store, ())
    assert "fused_with" not in alone["flow"]
    assert describe_priors(PriorConfig(), store, ())["flow"] == {"backend": "dis"}
