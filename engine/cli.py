"""Command-line interface: ``python -m engine <command> ...``.

Each command lives in ``engine/commands/<name>.py`` and exposes ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args, reporter) -> int | None``. Modules import
their heavy dependencies (torch, cv2, ...) inside ``run`` so ``--help`` stays instant.
To add a command, add its module name to :data:`COMMANDS`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys

from . import __version__
from .errors import EngineError, describe_os_error
from .protocol import Reporter

#: Command modules under ``engine.commands``, in the order ``--help`` lists them.
COMMANDS = (
    "version",
    "selftest",
    "init",
    "train",
    "render",
    "eval",
    "report",
    "export",
    "finetune",
    "models",
)


#: Commands that never import torch (kept fast: the add-on's model manager runs ``models``).
TORCH_FREE_COMMANDS = ("version", "models")


def _common_options() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--jsonl", action="store_true",
                        help="write progress/log/result/error events as JSON lines on stdout (used by the add-on)")
    common.add_argument("--quiet", action="store_true", help="no progress bars; warnings and errors only")
    common.add_argument("--threads", type=int, default=None,
                        help="CPU threads for torch and the CPU rasteriser (default: all cores)")
    return common


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m engine",
        description="Motion Splats engine: monocular video -> node-driven dynamic Gaussian splats.",
    )
    parser.add_argument("--version", action="version", version=f"motion-splats engine {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    common = _common_options()
    for name in COMMANDS:
        module = importlib.import_module(f".commands.{name}", __package__)
        cmd = sub.add_parser(name, help=module.HELP, description=module.__doc__, parents=[common],
                             formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(cmd)
        cmd.set_defaults(_module=module)
    return parser


def _raise_keyboard_interrupt(signum, frame):  # SIGTERM -> same clean path as Ctrl-C
    raise KeyboardInterrupt


class _ReporterHandler(logging.Handler):
    """Engine modules' ``logging`` warnings as the reporter's warning events (one line each),
    so library code without a reporter (e.g. the rasteriser's backend choice) is heard."""

    def __init__(self, reporter: Reporter):
        super().__init__(logging.WARNING)
        self.reporter = reporter

    def emit(self, record: logging.LogRecord) -> None:
        self.reporter.log(record.getMessage(), "warning")


def forward_warnings(reporter: Reporter) -> logging.Handler:
    """Route warnings logged under this package (``engine.*``) to ``reporter``; returns the handler."""
    logger = logging.getLogger(__package__)
    for old in [h for h in logger.handlers if isinstance(h, _ReporterHandler)]:
        logger.removeHandler(old)
    handler = _ReporterHandler(reporter)
    logger.addHandler(handler)  # a handler here also keeps logging's last-resort stderr copy away
    return handler


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    reporter = Reporter(jsonl=args.jsonl, quiet=args.quiet)
    handler = forward_warnings(reporter)
    try:
        return _run(args, reporter)
    finally:
        logging.getLogger(__package__).removeHandler(handler)


def _run(args, reporter: Reporter) -> int:
    if args.threads is not None and not 1 <= args.threads <= 1024:
        reporter.error(f"--threads must be between 1 and 1024 (got {args.threads})", fix="e.g. --threads 4")
        return 2
    if args.threads:
        import os

        os.environ["MOTION_SPLATS_THREADS"] = str(args.threads)
    if args.command not in TORCH_FREE_COMMANDS:
        from .runtime import configure_torch

        # process-wide torch state lives here, not in library objects (threads: the CPU
        # rasteriser follows torch's count; deterministic CPU kernels: bitwise --resume)
        configure_torch(args.threads, deterministic=True if getattr(args, "device", None) == "cpu" else None)
    signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
    # Cancel sends SIGINT first. A process started with SIGINT ignored (a background job of a
    # non-interactive shell, some launchers) inherits SIG_IGN, and Python then never raises
    # KeyboardInterrupt: install the default handler explicitly.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code = args._module.run(args, reporter)
        return int(code or 0)
    except EngineError as exc:
        reporter.error(getattr(exc, "message", str(exc)), path=getattr(exc, "path", None), fix=getattr(exc, "fix", None))
        return exc.exit_code
    except OSError as exc:  # a write failed: read-only or full disk, a parent that is a file, ...
        message, path, fix = describe_os_error(exc)
        reporter.error(message, path=path, fix=fix)
        return 2
    except KeyboardInterrupt:
        resumable = args.command == "train"  # the only command with --resume
        reporter.error("interrupted; state saved where the command supports it",
                       fix="re-run with --resume" if resumable else "run the command again")
        return 130
    except Exception as exc:  # report, then let the traceback reach stderr for bug reports
        reporter.error(f"internal error: {type(exc).__name__}: {exc}")
        if not args.jsonl:
            raise
        import traceback

        traceback.print_exc(file=sys.stderr)
        return 1
