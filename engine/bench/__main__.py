"""``python -m engine.bench <name> [--json] ...`` dispatcher."""

from __future__ import annotations

import argparse
import importlib
import sys

from .common import print_rows

#: Benchmark modules under ``engine.bench``; add yours here.
BENCHES: tuple[str, ...] = ("raster", "nodes", "priors", "quality", "train", "build", "cycles", "solve")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m engine.bench", description="Motion Splats benchmarks.")
    sub = parser.add_subparsers(dest="bench", metavar="BENCH")
    sub.required = True
    for name in BENCHES:
        module = importlib.import_module(f".{name}", __package__)
        cmd = sub.add_parser(name, help=module.HELP, description=module.__doc__,
                             formatter_class=argparse.RawDescriptionHelpFormatter)
        cmd.add_argument("--json", action="store_true", help="print one JSON object per row")
        module.add_arguments(cmd)
        cmd.set_defaults(_module=module)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from ..runtime import configure_torch

    # process-wide torch state, as `python -m engine` sets it (engine/runtime.py)
    configure_torch(deterministic=True if getattr(args, "device", None) == "cpu" else None)
    rows = args._module.run(args)
    print_rows(rows, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
