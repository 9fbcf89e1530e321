"""Manage the optional ONNX models behind the priors (registry, per-user cache).

Examples::

    python -m engine models list                 # every known model: role, size, licence, installed?
    python -m engine models fetch raft-small     # install (shipped copy or resumable download)
    python -m engine models verify               # re-hash installed models against the registry
    python -m engine models remove dinov2-small  # delete a model (and any partial download)

Installed models are used by ``train``/``init`` for every prior not set with a
``--*-model``/``--*-path`` flag (``--no-models`` turns that off). Nothing downloads
unless you run ``fetch``. The cache is per user (``--dir`` or $MOTION_SPLATS_MODELS moves it).
"""

HELP = "list, fetch, verify or remove the optional ONNX models for the priors"


def add_arguments(parser):
    parser.add_argument("action", choices=("list", "fetch", "verify", "remove"))
    parser.add_argument("names", nargs="*", metavar="NAME", help="model name(s) (verify/remove: default all)")
    parser.add_argument("--dir", help="model cache folder (default: the per-user cache, or $MOTION_SPLATS_MODELS)")
    parser.add_argument("--url", help="fetch from this URL instead of the registry's (a mirror)")
    parser.add_argument("--timeout", type=float, default=30.0,
                        help="seconds without data before a download stops (it resumes on the next fetch)")


def _row(spec, state) -> dict:
    return {"name": spec.name, "role": spec.role, "status": state.status, "size": spec.size_text,
            "license": spec.license, "non_commercial": spec.non_commercial, "shipped": spec.shipped_path is not None,
            "fetchable": spec.fetchable, "path": str(state.path), "partial_bytes": state.partial_bytes,
            "title": spec.title}


def _print_table(rows, root):
    print(f"model cache: {root}")
    for r in rows:
        flag = "  NON-COMMERCIAL" if r["non_commercial"] else ""
        how = "shipped" if r["shipped"] else ("download" if r["fetchable"] else "bring your own")
        status = r["status"] + (f" ({r['partial_bytes']} bytes)" if r["status"] == "partial" else "")
        print(f"{r['name']:<26} {r['role']:<7} {status:<12} {r['size']:>10}  {how:<14} {r['license']}{flag}")


def run(args, reporter):
    from ..errors import InputError
    from ..models import ModelStore, fetch, get_spec, load_registry

    registry = load_registry()
    store = ModelStore(args.dir)
    names = args.names or []
    specs = [get_spec(n, registry) for n in names] if names else list(registry)
    if args.action == "list":
        rows = [_row(s, store.state(s)) for s in specs]
        if reporter.jsonl:
            reporter.result(root=str(store.root), models=rows)
        else:
            _print_table(rows, store.root)
        return 0
    if args.action == "fetch":
        if not names:
            raise InputError("fetch needs a model name", None, "e.g. python -m engine models fetch raft-small "
                                                               "(see: python -m engine models list)")
        done = []
        for spec in specs:
            info = fetch(spec, store, reporter, timeout=args.timeout, urls=[args.url] if args.url else None)
            reporter.log(f"{spec.name}: {'already installed' if info['already'] else 'installed'} at {info['path']} "
                         f"(sha256 {info['sha256']})")
            done.append(info)
        reporter.result(root=str(store.root), fetched=done)
        return 0
    if args.action == "verify":
        checked = [store.verify(s) for s in specs if names or store.model_path(s).is_file()]
        for c in checked:
            reporter.log(f"{c['name']}: {c['status']} sha256 {c['sha256']} ({c['bytes']} bytes)"
                         + (f", registry {c['expected']}" if c["status"] == "mismatch" else ""),
                         level="info" if c["status"] in ("ok", "unpinned") else "warning")
        bad = [c["name"] for c in checked if c["status"] in ("mismatch", "missing")]
        if bad:  # the error is the last event (no result before it)
            raise InputError(f"{', '.join(bad)}: missing or not matching the registry", store.root,
                             f"python -m engine models remove {' '.join(bad)} && "
                             f"python -m engine models fetch {' '.join(bad)}")
        reporter.result(root=str(store.root), verified=checked)
        return 0
    removed = [s.name for s in specs if store.remove(s)]
    reporter.log(f"removed: {', '.join(removed) or 'nothing'}")
    reporter.result(root=str(store.root), removed=removed)
    return 0
