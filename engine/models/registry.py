"""The model registry: which ONNX models the priors know, read from ``registry.json``.

The registry is data (``registry.json`` beside this file), not code: each entry names a
model, its prior ``role`` (``tokens`` | ``depth`` | ``mask`` | ``flow`` | ``tracks``), the
file name it is installed under, download URLs (tried in order; empty when none is
published), the exact size and SHA-256 where known (``null`` = unknown: the download is
then checked for size only when known and its hash is recorded, not compared), the
licence (``non_commercial`` flags licences artists cannot use for paid work), the ONNX
input contract, an optional sidecar JSON written next to the model (see
``engine/priors/onnx_util.py``), and the citation. A ``shipped`` path (relative to the
``engine`` package) marks a model that ships inside the product: fetching it copies the
shipped file, no network. Files named in ``$MOTION_SPLATS_REGISTRY`` (same format,
``os.pathsep``-separated) add your own models after the built-in ones.

Standard library only, so the Blender add-on can import it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError

#: Prior roles a model can fill, in the order the priors run (see engine/priors/cache.py).
ROLES = ("flow", "tracks", "depth", "mask", "tokens")

REGISTRY_FILE = Path(__file__).with_name("registry.json")
#: Environment variable listing extra registry files (``os.pathsep``-separated).
EXTRA_ENV = "MOTION_SPLATS_REGISTRY"
ENGINE_ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class ModelSpec:
    """One registry entry (see the module docstring for the fields)."""

    name: str
    role: str
    title: str
    file: str
    license: str
    urls: tuple = ()
    shipped: str | None = None
    bytes: int | None = None
    approx_mb: float | None = None
    sha256: str | None = None
    non_commercial: bool = False
    source: str = ""
    contract: str = ""
    sidecar: dict | None = None
    citation: str = ""
    note: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def shipped_path(self) -> Path | None:
        """Absolute path of the copy shipped in the product, or None (not shipped / absent)."""
        if not self.shipped:
            return None
        path = ENGINE_ROOT / self.shipped
        return path if path.is_file() else None

    @property
    def fetchable(self) -> bool:
        """Whether ``models fetch`` can obtain it (a shipped copy or a URL)."""
        return bool(self.urls) or self.shipped_path is not None

    @property
    def size_text(self) -> str:
        """Human size: exact when known, else the approximate size, else '?'."""
        if self.bytes:
            return f"{self.bytes / 1e6:.1f} MB"
        return f"~{self.approx_mb:g} MB" if self.approx_mb else "?"


_FIELDS = set(ModelSpec.__dataclass_fields__) - {"extra"}


def _spec(entry: dict, source: Path) -> ModelSpec:
    missing = [k for k in ("name", "role", "title", "file", "license") if not entry.get(k)]
    if missing:
        raise InputError(f"registry entry {entry.get('name', '?')!r} lacks {', '.join(missing)}", source,
                         "fix the registry JSON")
    if entry["role"] not in ROLES:
        raise InputError(f"registry entry {entry['name']!r} has unknown role {entry['role']!r}", source,
                         f"use one of {', '.join(ROLES)}")
    sha = entry.get("sha256")
    if sha is not None and (len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha)):
        raise InputError(f"registry entry {entry['name']!r}: sha256 must be 64 lower-case hex digits or null",
                         source, "fix the registry JSON")
    known = {k: v for k, v in entry.items() if k in _FIELDS}
    known["urls"] = tuple(entry.get("urls") or ())
    return ModelSpec(**known, extra={k: v for k, v in entry.items() if k not in _FIELDS})


def _read(path: Path) -> list[ModelSpec]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the model registry ({exc})", path,
                         f"fix or remove the file (${EXTRA_ENV} names extra registries)") from exc
    if not isinstance(data, dict) or not isinstance(data.get("models"), list):
        raise InputError('a model registry is a JSON object with a "models" list', path, "see registry.json")
    return [_spec(e, path) for e in data["models"]]


def load_registry(path: str | Path | None = None) -> tuple[ModelSpec, ...]:
    """Read the registry: ``path``, else the built-in ``registry.json`` followed by the entries
    of the files listed in ``$MOTION_SPLATS_REGISTRY`` (your own models, same format).

    Returns
    -------
    tuple of ModelSpec, in file order (the first installed model of a role is the one
    ``auto`` picks, so built-in entries come first).
    """
    paths = [Path(path)] if path else [REGISTRY_FILE] + [Path(p) for p in
                                                         os.environ.get(EXTRA_ENV, "").split(os.pathsep) if p]
    specs = [s for p in paths for s in _read(p)]
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"model registry lists {', '.join(dup)} twice", paths[-1], "give every model a unique name")
    return tuple(specs)


def get_spec(name: str, registry=None) -> ModelSpec:
    """The entry called ``name``; an :class:`InputError` listing the known names otherwise."""
    specs = registry if registry is not None else load_registry()
    for spec in specs:
        if spec.name == name:
            return spec
    raise InputError(f"unknown model {name!r}", None,
                     f"use one of: {', '.join(s.name for s in specs)} (python -m engine models list)")
