"""Model manager downloads against a local HTTP server (127.0.0.1, never the internet):
right hash, wrong hash, truncated, 404, offline, dropped connection -> resume, stall, disk full."""

from __future__ import annotations

import errno
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from engine.errors import Cancelled
from engine.models import DownloadError, ModelSpec, ModelStore, fetch, load_registry
from tests.engine._model_server import ModelServer, tiny_onnx_bytes

REPO = Path(__file__).resolve().parents[2]


def _spec(data: bytes, url: str, *, sha=True, size=True, name="tiny-depth", sidecar=None) -> ModelSpec:
    return ModelSpec(name=name, role="depth", title="tiny", file="tiny.onnx", license="MIT", urls=(url,),
                     bytes=len(data) if size else None, sha256=hashlib.sha256(data).hexdigest() if sha else None,
                     sidecar=sidecar)


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


@pytest.fixture()
def server():
    with ModelServer() as srv:
        yield srv


def test_right_hash_installs_atomically_with_sidecar_and_record(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/tiny.onnx", data), sidecar={"input_size": [32, 32]})
    store = ModelStore(tmp_path / "models")
    info = fetch(spec, store)
    assert info["sha256"] == spec.sha256 and not info["already"]
    assert store.model_path(spec).read_bytes() == data
    assert _files(store.root) == ["tiny-depth/installed.json", "tiny-depth/tiny.onnx", "tiny-depth/tiny.onnx.json"]
    assert store.state(spec).status == "installed"
    assert store.verify(spec)["status"] == "ok"
    # a second fetch does nothing (no request)
    n = len(server.requests)
    assert fetch(spec, store)["already"] and len(server.requests) == n


def test_wrong_hash_is_deleted_and_nothing_installed(server, tmp_path):
    good, bad = tiny_onnx_bytes(seed=0), tiny_onnx_bytes(seed=1)
    assert len(good) == len(bad)
    spec = _spec(good, server.add("/bad.onnx", bad))
    store = ModelStore(tmp_path / "models")
    with pytest.raises(DownloadError, match="SHA-256 .* does not match") as err:
        fetch(spec, store)
    assert "\n" not in err.value.message and str(server.url("/bad.onnx")) in err.value.message
    assert _files(store.root) == [] and store.state(spec).status == "missing"


def test_truncated_file_fails_size_check(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/trunc.onnx", data[:-1000]))
    store = ModelStore(tmp_path / "models")
    with pytest.raises(DownloadError, match=f"expected {len(data)}"):
        fetch(spec, store)
    assert _files(store.root) == []
    # unknown size: the hash catches it
    spec = _spec(data, server.url("/trunc.onnx"), size=False)
    with pytest.raises(DownloadError, match="SHA-256"):
        fetch(spec, store)
    assert _files(store.root) == []


def test_http_404_and_offline_are_one_line(server, tmp_path):
    data = tiny_onnx_bytes()
    store = ModelStore(tmp_path / "models")
    with pytest.raises(DownloadError, match="HTTP 404") as err:
        fetch(_spec(data, server.url("/missing.onnx")), store)
    assert "--depth-model" in err.value.message and "\n" not in err.value.message
    with pytest.raises(DownloadError, match="cannot reach the server"):
        fetch(_spec(data, "http://127.0.0.1:9/nothing-listens-here.onnx"), store)
    assert _files(store.root) == []


def test_mirror_after_a_dead_url(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = ModelSpec(name="m", role="depth", title="m", file="m.onnx", license="MIT",
                     urls=(server.url("/gone.onnx"), server.add("/m.onnx", data)),
                     sha256=hashlib.sha256(data).hexdigest())
    info = fetch(spec, ModelStore(tmp_path))
    assert info["source"].endswith("/m.onnx")


def test_dropped_connection_keeps_part_and_resumes(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/drop.onnx", data, mode="drop"))
    store = ModelStore(tmp_path / "models")
    with pytest.raises(DownloadError, match="interrupted after .* bytes") as err:
        fetch(spec, store)
    assert "resumes" in err.value.message
    part = store.part_path(spec)
    assert part.is_file() and 0 < part.stat().st_size < len(data)
    assert store.state(spec).status == "partial" and not store.model_path(spec).exists()
    have = part.stat().st_size
    info = fetch(spec, store)  # resumes with a Range request
    assert server.requests[-1] == ("/drop.onnx", f"bytes={have}-")
    assert info["sha256"] == spec.sha256 and not part.exists()
    assert store.model_path(spec).read_bytes() == data


def test_server_ignoring_range_restarts_cleanly(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/norange.onnx", data, mode="norange"))
    store = ModelStore(tmp_path / "models")
    store.folder(spec).mkdir(parents=True)
    store.part_path(spec).write_bytes(b"garbage" * 10)  # a stale part: a 200 reply replaces it
    assert fetch(spec, store)["sha256"] == spec.sha256


def test_stalled_server_times_out_and_keeps_part(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/stall.onnx", data, mode="stall"))
    store = ModelStore(tmp_path / "models")
    with pytest.raises(DownloadError, match="stalled"):
        fetch(spec, store, timeout=0.5)
    assert store.part_path(spec).stat().st_size == 100 and not store.model_path(spec).exists()


def test_disk_full_removes_the_part(server, tmp_path, monkeypatch):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/tiny.onnx", data))
    store = ModelStore(tmp_path / "models")
    import engine.models.download as D

    real_open = open

    class Full:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.fh.close()

        def seek(self, *a):
            return self.fh.seek(*a)

        def truncate(self, *a):
            return self.fh.truncate(*a)

        def write(self, block):
            self.fh.write(block[:10])
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(D, "open", lambda *a, **k: Full(real_open(*a, **k)), raising=False)
    with pytest.raises(DownloadError, match="disk full"):
        fetch(spec, store)
    assert _files(store.root) == []


def test_ctrl_c_keeps_part_for_resume(server, tmp_path, monkeypatch):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/tiny.onnx", data))
    store = ModelStore(tmp_path / "models")
    import engine.models.download as D

    def interrupted(*_a, **_k):
        store.part_path(spec).write_bytes(data[:500])
        raise KeyboardInterrupt

    monkeypatch.setattr(D, "_transfer", interrupted)
    with pytest.raises(Cancelled, match="500 bytes kept"):
        fetch(spec, store)
    monkeypatch.undo()
    assert fetch(spec, store)["sha256"] == spec.sha256
    assert server.requests[-1][1] == "bytes=500-"


def test_model_without_download_says_what_to_do(tmp_path):
    spec = next(s for s in load_registry() if s.name == "bootstapir")
    with pytest.raises(DownloadError, match="no published download") as err:
        fetch(spec, ModelStore(tmp_path))
    assert "--tracks-model" in err.value.message


def test_cli_fetch_verify_remove_with_extra_registry(server, tmp_path):
    """The CLI end to end: a user registry (MOTION_SPLATS_REGISTRY) + a cache folder; wrong
    bytes on disk make verify fail with one line; remove clears everything."""
    data = tiny_onnx_bytes()
    reg = tmp_path / "mine.json"
    reg.write_text('{"models": [{"name": "tiny-depth", "role": "depth", "title": "t", "file": "t.onnx", '
                   f'"license": "MIT", "urls": ["{server.add("/t.onnx", data)}"], "bytes": {len(data)}, '
                   f'"sha256": "{hashlib.sha256(data).hexdigest()}"}}]}}')
    env = {**os.environ, "MOTION_SPLATS_REGISTRY": str(reg), "MOTION_SPLATS_MODELS": str(tmp_path / "models")}

    def engine(*args):
        return subprocess.run([sys.executable, "-m", "engine", "models", *args], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=120)

    res = engine("list")
    assert res.returncode == 0 and "tiny-depth" in res.stdout and "missing" in res.stdout
    assert "NON-COMMERCIAL" in res.stdout  # cotracker3 is flagged
    res = engine("fetch", "tiny-depth")
    assert res.returncode == 0, res.stderr
    assert engine("verify").returncode == 0
    path = tmp_path / "models" / "tiny-depth" / "t.onnx"
    path.write_bytes(data[:-1] + b"\0")
    res = engine("verify", "tiny-depth")
    last = res.stderr.strip().splitlines()[-1]
    assert res.returncode == 2 and last.startswith("error: ") and "tiny-depth: missing or not matching" in last
    res = engine("fetch", "nope")
    assert res.returncode == 2 and "unknown model 'nope'" in res.stderr
    assert engine("remove", "tiny-depth").returncode == 0
    assert not (tmp_path / "models" / "tiny-depth").exists()


def test_move_into_place_failure_is_one_line_and_leaves_no_part(server, tmp_path):
    data = tiny_onnx_bytes()
    spec = _spec(data, server.add("/tiny.onnx", data))
    store = ModelStore(tmp_path / "models")
    store.model_path(spec).mkdir(parents=True)  # something that os.replace cannot overwrite
    (store.model_path(spec) / "x").write_text("x")
    with pytest.raises(DownloadError, match="cannot move tiny-depth into place"):
        fetch(spec, store)
    assert not store.part_path(spec).exists() and store.read_record(spec) is None


def test_registry_is_well_formed():
    specs = load_registry()
    assert {s.role for s in specs} == {"flow", "tokens", "depth", "mask", "tracks"}
    for s in specs:
        assert all(u.startswith("https://") for u in s.urls), s.name
        assert s.fetchable or s.note or s.shipped, f"{s.name}: say how to get it"
        assert s.license
    nc = {s.name for s in specs if s.non_commercial}
    assert nc == {"cotracker3"} and all("NC" in s.license for s in specs if s.name in nc)
    assert next(s for s in specs if s.name == "raft-small").shipped


def test_shipped_raft_small_matches_the_registry(tmp_path):
    """`models fetch raft-small` copies the shipped file (no network) and its hash is the registry's."""
    spec = next(s for s in load_registry() if s.name == "raft-small")
    if spec.shipped_path is None:
        pytest.skip("RAFT-small is not shipped in this checkout")
    info = fetch(spec, ModelStore(tmp_path))
    assert info["sha256"] == spec.sha256 and info["source"] == str(spec.shipped_path)
