"""Initialise nodes for a clip (priors -> MANI -> spline trajectories) and write them
into a result bundle, so Blender can show the nodes before training.

Example::

    python -m engine init data/clip --out out/run
"""

from ._train_options import (add_clip_options, check_run_output, clip_options, config_from_args,
                             prior_config_from_args)

HELP = "compute priors and initial nodes + splines; write them into a bundle"


def add_arguments(parser):
    add_clip_options(parser)


def run(args, reporter):
    import dataclasses
    from pathlib import Path

    from .. import bundle as B
    from ..lock import hold
    from ..pipeline import bundle_scene, initial_nodes, open_clip, prepare, resolve_motion_init

    cfg = config_from_args(args)
    check_run_output(args)
    out = Path(args.out)
    with hold(out):
        clip = open_clip(args.clip, reporter, **clip_options(args))
        prep = prepare(clip, cfg, prior_config_from_args(args), cache_dir=args.cache or out / "cache",
                       reporter=reporter)
        cfg = dataclasses.replace(cfg, motion_init=resolve_motion_init(prep, cfg))  # record what ran
        nodes = initial_nodes(prep, cfg)
        if args.overwrite:  # validate first, replace last
            B.clear_run_outputs(out)
        B.save_bundle(out, bundle_scene(prep, cfg, stage="init"), nodes)
    p_dyn = nodes.p_dyn if nodes.p_dyn is not None else None
    reporter.result(bundle=str(out), nodes=nodes.count, keys=int(nodes.key_times.shape[0]),
                    dynamic_nodes=None if p_dyn is None else int((p_dyn > 0.5).sum()),
                    priors_recomputed=prep.priors.recomputed)
    return 0
