"""Backend ``auto``: fill the prior roles the user left open with installed models, and
describe which model (name + SHA-256) or weight-free backend produced each prior.

:func:`resolve_prior_models` only reads the cache (never downloads). A role counts as
set by the user when its backend is not the weight-free default or a precomputed file
is given; those are left alone. :func:`describe_priors` is what ``scene.json`` records
under ``priors`` and the report shows.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from .registry import ModelSpec, load_registry
from .store import ModelStore, sha256_file

#: role -> (backend field, model field, precomputed-file field or None). ``flow`` exists
#: once the priors offer a learned flow backend (PriorConfig.flow_backend).
ROLE_FIELDS = {
    "tokens": ("tokens_backend", "tokens_model", None),
    "tracks": ("tracks_backend", "tracks_model", "tracks_path"),
    "depth": ("depth_backend", "depth_model", "depth_path"),
    "mask": ("mask_backend", "mask_model", "mask_path"),
    "flow": ("flow_backend", "flow_model", None),
}


def _default_backend(cfg, field: str):
    for f in dataclasses.fields(cfg):
        if f.name == field:
            return f.default
    return None


def role_is_open(cfg, role: str) -> bool:
    """True when ``cfg`` runs the default (or ``auto``) backend for ``role`` with no model and
    no precomputed file, i.e. the user did not choose."""
    backend, model, path = ROLE_FIELDS[role]
    if not hasattr(cfg, backend):
        return False
    if path is not None and getattr(cfg, path, None):
        return False
    return getattr(cfg, backend) in (_default_backend(cfg, backend), "auto") and not getattr(cfg, model, None)


def shipped_for_role(role: str, registry) -> tuple[ModelSpec, Path] | None:
    """The first registry model of ``role`` that ships inside the product (and is present)."""
    for spec in registry:
        if spec.role == role and spec.shipped_path is not None:
            return spec, spec.shipped_path
    return None


def installed_for_role(role: str, store: ModelStore | None = None, registry=None) -> tuple[ModelSpec, Path] | None:
    """The first registry model of ``role`` that is installed (and unchanged) in the cache."""
    store = store or ModelStore()
    for spec in registry if registry is not None else load_registry():
        if spec.role == role:
            path = store.installed_path(spec)
            if path is not None:
                return spec, path
    return None


def resolve_prior_models(cfg, store: ModelStore | None = None, registry=None, reporter=None, explicit=()):
    """Return a copy of the PriorConfig ``cfg`` with every open role using its installed model.

    A role with an installed model (cache) switches to backend ``"onnx"`` with that file;
    a role whose backend is ``"auto"`` and that has none installed takes the model shipped
    in the product (RAFT-small for flow) when there is one; other roles keep their
    weight-free backend. Roles in ``explicit`` (the user named their backend, e.g.
    ``--flow-backend dis``) are left alone. Nothing is downloaded.
    """
    store = store or ModelStore()
    registry = registry if registry is not None else load_registry()
    changes = {}
    for role, (backend, model, _path) in ROLE_FIELDS.items():
        if role in explicit or not role_is_open(cfg, role):
            continue
        found = installed_for_role(role, store, registry)
        if found is None and getattr(cfg, backend) == "auto":
            found = shipped_for_role(role, registry)
        if found is not None:
            spec, path = found
            changes[backend], changes[model] = "onnx", str(path)
            if reporter is not None:
                reporter.log(f"{role} prior: installed model {spec.name} ({path})")
    return dataclasses.replace(cfg, **changes) if changes else cfg


def _model_identity(path: str, store: ModelStore, registry) -> dict:
    """Name + SHA-256 of a model file: from the cache record when it is a cached model, else hashed."""
    p = Path(path)
    for spec in registry:
        if store.model_path(spec) == p and store.installed_path(spec) is not None:
            rec = store.read_record(spec) or {}
            return {"model": spec.name, "sha256": rec.get("sha256"), "license": spec.license, "file": str(p)}
    sha = sha256_file(p) if p.is_file() else None
    for spec in registry:
        if sha is not None and spec.sha256 == sha:
            return {"model": spec.name, "sha256": sha, "license": spec.license, "file": str(p)}
    return {"model": p.stem, "sha256": sha, "license": None, "file": str(p)}


def describe_priors(cfg, store: ModelStore | None = None, registry=None) -> dict:
    """Which backend produced each prior: ``{role: {"backend", "model", "sha256", "license", "file"}}``.

    Weight-free roles give ``{"backend": <name>}``; a precomputed file gives
    ``{"backend": "file", "file": path}``. Roles the PriorConfig does not have are left out.
    A learned flow fused per pixel with DIS (``PriorConfig.flow_fuse_dis``) adds
    ``"fused_with": "dis"``.
    """
    store = store or ModelStore()
    registry = registry if registry is not None else load_registry()
    out = {}
    for role, (backend, model, path) in ROLE_FIELDS.items():
        if not hasattr(cfg, backend):
            continue
        if path is not None and getattr(cfg, path, None):
            out[role] = {"backend": "file", "file": str(getattr(cfg, path))}
        elif getattr(cfg, model, None):
            out[role] = {"backend": getattr(cfg, backend), **_model_identity(getattr(cfg, model), store, registry)}
        else:
            name, file = _effective_backend(role, getattr(cfg, backend))
            out[role] = {"backend": name, **(_model_identity(file, store, registry) if file else {})}
        if role == "flow" and "file" in out[role] and getattr(cfg, "flow_fuse_dis", False):
            out[role]["fused_with"] = "dis"  # engine.priors.flow.FusedFlowSource
    return out


def _effective_backend(role: str, backend: str) -> tuple[str, str | None]:
    """``(backend, model path)`` an unresolved ``auto`` runs as: the priors decide (today only
    flow has ``auto``: the shipped RAFT-small when usable, else DIS)."""
    if backend != "auto" or role != "flow":
        return backend, None
    try:
        from ..priors.flow import resolve_flow_backend
    except ImportError:
        return backend, None
    return resolve_flow_backend("auto", None)
