"""The Models box of the add-on preferences: Download refused offline, a background download
from a local 127.0.0.1 server (never the internet) with progress in the box, Remove."""

from __future__ import annotations

import hashlib
import json

import bpy
import pytest

from tests.addon._support import registered, user_dir, clean_jobs  # noqa: F401 (fixtures)
from tests.engine._model_server import ModelServer, tiny_onnx_bytes


class _Stub:
    """A layout that accepts every call and records label texts (headless draw)."""

    def __init__(self, texts):
        object.__setattr__(self, "texts", texts)

    def __getattr__(self, name):
        def call(*args, **kwargs):
            if name == "label":
                self.texts.append(kwargs.get("text", ""))
            return _Stub(self.texts)
        return call

    def __setattr__(self, name, value):
        pass


def _draw(extension) -> list[str]:
    texts: list[str] = []
    extension.addon.models_ui.draw(_Stub(texts), bpy.context)
    return texts


@pytest.fixture()
def local_models(tmp_path, monkeypatch):
    """A user registry with one model served from 127.0.0.1 and an empty model cache."""
    data = tiny_onnx_bytes()
    with ModelServer() as srv:
        reg = tmp_path / "reg.json"
        reg.write_text(json.dumps({"models": [{
            "name": "tiny-depth", "role": "depth", "title": "t", "file": "tiny-depth.onnx", "license": "MIT",
            "urls": [srv.add("/d.onnx", data)], "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}]}))
        monkeypatch.setenv("MOTION_SPLATS_REGISTRY", str(reg))
        monkeypatch.setenv("MOTION_SPLATS_MODELS", str(tmp_path / "models"))
        yield tmp_path / "models" / "tiny-depth" / "tiny-depth.onnx", data, srv


def test_download_refused_offline(extension, registered, local_models):
    assert bpy.app.online_access is False  # headless bpy default
    with pytest.raises(RuntimeError, match="Online access is disabled"):
        bpy.ops.motion_splats.model_download(name="tiny-depth")
    assert extension.addon.jobs.latest("model:tiny-depth") is None
    texts = _draw(extension)
    assert any("Online access is off" in t for t in texts)
    assert any(t.startswith("tiny-depth") for t in texts) and "not installed" in texts
    assert any("NON-COMMERCIAL" in t for t in texts)  # cotracker3 is flagged in the box


def test_download_in_background_then_remove(extension, registered, local_models, monkeypatch):
    path, data, srv = local_models
    ui = extension.addon.models_ui
    monkeypatch.setattr(ui, "online_access", lambda: True)  # the user allowed online access
    assert bpy.ops.motion_splats.model_download(name="tiny-depth") == {"FINISHED"}
    jobs = extension.addon.jobs
    job = jobs.latest("model:tiny-depth")
    assert job is not None
    _draw(extension)  # drawing while it runs does not fail
    jobs.wait(job, timeout=120)
    assert job.state == "finished", job.error_summary()
    assert path.read_bytes() == data
    assert any(r[0] == "/d.onnx" for r in srv.requests)
    texts = _draw(extension)
    assert "installed" in texts
    assert bpy.ops.motion_splats.model_remove(name="tiny-depth") == {"FINISHED"}
    assert not path.parent.exists()


def test_failed_download_shows_one_line(extension, registered, local_models, monkeypatch):
    _path, _data, srv = local_models
    srv.files.clear()  # the server now answers 404
    monkeypatch.setattr(extension.addon.models_ui, "online_access", lambda: True)
    assert bpy.ops.motion_splats.model_download(name="tiny-depth") == {"FINISHED"}
    job = extension.addon.jobs.wait(extension.addon.jobs.latest("model:tiny-depth"), timeout=120)
    assert job.state == "failed" and "HTTP 404" in " ".join(job.error_summary())
    assert any("HTTP 404" in t for t in _draw(extension))


def test_unknown_model_and_bring_your_own(extension, registered, local_models, monkeypatch):
    monkeypatch.setattr(extension.addon.models_ui, "online_access", lambda: True)
    with pytest.raises(RuntimeError, match="unknown model"):
        bpy.ops.motion_splats.model_download(name="nope")
    with pytest.raises(RuntimeError, match="no ONNX export"):
        bpy.ops.motion_splats.model_download(name="bootstapir")
