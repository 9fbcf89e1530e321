"""Reconstruct a clip: cameras -> priors -> nodes (MANI) -> training -> result bundle.

Examples::

    python -m engine train data/clip --out out/run                 # preview preset, CPU
    python -m engine train data/clip --out out/run --resume        # continue after Cancel
    python -m engine train data/clip --out out/fps --init fps --motion mlp   # ablation

Progress is a tqdm bar on a terminal, or JSON lines with --jsonl. Ctrl-C (or SIGTERM)
stops after the current step and writes a checkpoint; --resume continues it.
"""

from ._train_options import (add_clip_options, check_run_output, clip_options, config_from_args,
                             prior_config_from_args)

HELP = "reconstruct a clip into a trained result bundle (resumable)"


def add_arguments(parser):
    add_clip_options(parser)
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint in --out")


def run(args, reporter):
    from ..lock import hold
    from ..pipeline import reconstruct

    cfg = config_from_args(args)
    check_run_output(args)
    with hold(args.out):
        result = reconstruct(args.clip, args.out, cfg, reporter, resume=args.resume, overwrite=args.overwrite,
                             cache_dir=args.cache, prior_config=prior_config_from_args(args),
                             clip_options=clip_options(args))
        result["report"] = _write_report(result.get("bundle", args.out), reporter, cfg.device, cfg.backend)
    reporter.result(**result)
    return 0


def _write_report(bundle, reporter, device: str = "auto", backend: str = "auto"):
    """<out>/report/report.html, evaluated on the training run's device and backend; a failed
    report is logged, never fails the run."""
    from ..errors import EngineError
    from ..report import write_report

    try:
        return str(write_report(bundle, device=device, backend=backend))
    except (EngineError, OSError, ValueError) as exc:
        reporter.log(f"report not written: {exc}", level="warning")
        return None
