"""The per-user model cache: where models live, what is installed, verify and remove.

Layout (``root`` = :func:`default_root` or an explicit folder)::

    <root>/<name>/<file>            the model, only ever moved in complete and checked
    <root>/<name>/<file>.json       the priors' sidecar (input size, layout, ...), if any
    <root>/<name>/installed.json    the install record: sha256, bytes, mtime_ns, url
    <root>/<name>/.<file>.part      an unfinished download (resumed by the next fetch)

A model counts as installed only when its file and its record agree on size and mtime
(cheap stat checks; :func:`verify` re-hashes). The record is written last, so a crash
between moving the file and recording it leaves a model that ``verify`` repairs or
reports, never a half-written file under the real name. Standard library only (the
Blender add-on imports it).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..fsutil import atomic_write_json
from .registry import ModelSpec

#: Environment variable that moves the model cache (tests, a bigger drive).
ROOT_ENV = "MOTION_SPLATS_MODELS"
RECORD = "installed.json"


def default_root() -> Path:
    """The platform's per-user cache folder for models (``$MOTION_SPLATS_MODELS`` overrides).

    Linux ``$XDG_CACHE_HOME/motion-splats/models`` (``~/.cache/...``), macOS
    ``~/Library/Caches/MotionSplats/models``, Windows ``%LOCALAPPDATA%\\MotionSplats\\models``.
    """
    override = os.environ.get(ROOT_ENV)
    if override:
        return Path(override).expanduser()
    home = Path.home()
    if sys.platform == "win32":
        return Path(os.environ.get("LOCALAPPDATA") or home / "AppData" / "Local") / "MotionSplats" / "models"
    if sys.platform == "darwin":
        return home / "Library" / "Caches" / "MotionSplats" / "models"
    return Path(os.environ.get("XDG_CACHE_HOME") or home / ".cache") / "motion-splats" / "models"


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class ModelState:
    """What the cache holds for one model. ``status``: installed | missing | partial | changed | unrecorded."""

    spec: ModelSpec
    status: str
    path: Path
    sha256: str | None = None
    bytes: int | None = None
    partial_bytes: int = 0


class ModelStore:
    """The model cache folder ``root`` (default :func:`default_root`)."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root is not None else default_root()

    # -- paths ---------------------------------------------------------------------------
    def folder(self, spec: ModelSpec) -> Path:
        return self.root / spec.name

    def model_path(self, spec: ModelSpec) -> Path:
        return self.folder(spec) / spec.file

    def part_path(self, spec: ModelSpec) -> Path:
        return self.folder(spec) / f".{spec.file}.part"

    def record_path(self, spec: ModelSpec) -> Path:
        return self.folder(spec) / RECORD

    # -- state ---------------------------------------------------------------------------
    def read_record(self, spec: ModelSpec) -> dict | None:
        try:
            data = json.loads(self.record_path(spec).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def state(self, spec: ModelSpec) -> ModelState:
        """Cheap state from stat calls and the record (no hashing)."""
        path, part = self.model_path(spec), self.part_path(spec)
        partial = part.stat().st_size if part.is_file() else 0
        if not path.is_file():
            return ModelState(spec, "partial" if partial else "missing", path, partial_bytes=partial)
        st, rec = path.stat(), self.read_record(spec)
        if rec is None:
            return ModelState(spec, "unrecorded", path, bytes=st.st_size, partial_bytes=partial)
        same = rec.get("bytes") == st.st_size and rec.get("mtime_ns") == st.st_mtime_ns
        return ModelState(spec, "installed" if same else "changed", path, sha256=rec.get("sha256"),
                          bytes=st.st_size, partial_bytes=partial)

    def installed_path(self, spec: ModelSpec) -> Path | None:
        """The model's path when it is installed and unchanged since, else None."""
        st = self.state(spec)
        return st.path if st.status == "installed" else None

    # -- changes -------------------------------------------------------------------------
    def install(self, spec: ModelSpec, finished: Path, sha256: str, url: str | None) -> Path:
        """Move a complete, checked download into place (atomic) and record it.

        Order: sidecar JSON, then ``os.replace`` of the file, then the record; the record
        is the commit point that makes the model count as installed.
        """
        path = self.model_path(spec)
        if spec.sidecar:
            atomic_write_json(Path(str(path) + ".json"), spec.sidecar)
        os.replace(finished, path)
        st = path.stat()
        atomic_write_json(self.record_path(spec), {
            "name": spec.name, "role": spec.role, "file": spec.file, "sha256": sha256, "bytes": st.st_size,
            "mtime_ns": st.st_mtime_ns, "url": url, "pinned": spec.sha256 is not None,
            "license": spec.license, "installed_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
        return path

    def remove(self, spec: ModelSpec) -> bool:
        """Delete the model, its sidecar, record and any partial download. True if anything was there."""
        folder = self.folder(spec)
        if not folder.exists():
            return False
        try:
            shutil.rmtree(folder)
        except OSError as exc:
            raise InputError(f"cannot remove {spec.name} ({exc.strerror or exc})", folder,
                             "close programs using the file and run remove again") from exc
        return True

    def verify(self, spec: ModelSpec) -> dict:
        """Re-hash an installed model and compare with the registry (or the record when unpinned).

        Returns ``{"name", "status", "sha256", "bytes", "expected"}``; status is ``ok``,
        ``unpinned`` (no registry hash: size/hash reported only), ``mismatch`` or ``missing``.
        A file that matches gets its record (re)written, so ``changed``/``unrecorded``
        files that are still right become installed again.
        """
        path = self.model_path(spec)
        if not path.is_file():
            return {"name": spec.name, "status": "missing", "sha256": None, "bytes": None, "expected": spec.sha256}
        digest, size = sha256_file(path), path.stat().st_size
        rec = self.read_record(spec) or {}
        expected = spec.sha256 or rec.get("sha256")
        size_ok = spec.bytes is None or spec.bytes == size
        if expected is not None and (digest != expected or not size_ok):
            status = "mismatch"
        else:
            status = "ok" if spec.sha256 else "unpinned"
            if rec.get("sha256") != digest or rec.get("bytes") != size or rec.get("mtime_ns") != path.stat().st_mtime_ns:
                st = path.stat()
                atomic_write_json(self.record_path(spec), {**rec, "name": spec.name, "role": spec.role,
                                                           "file": spec.file, "sha256": digest, "bytes": size,
                                                           "mtime_ns": st.st_mtime_ns,
                                                           "pinned": spec.sha256 is not None,
                                                           "license": spec.license})
        return {"name": spec.name, "status": status, "sha256": digest, "bytes": size, "expected": expected}
