"""Write an HTML report for a trained bundle (curves, held-out renders, node overlay).

Examples::

    python -m engine report out/run                      # -> out/run/report/report.html
    python -m engine report out/run --clip data/clip --out /tmp/r/report.html

The report folder is self-contained (report.html + PNG images); see engine/report.py.
"""

HELP = "write an HTML report (curves, held-out renders vs ground truth, node overlay, metrics)"


def add_arguments(parser):
    parser.add_argument("bundle", help="result bundle folder (from `train`)")
    parser.add_argument("--clip", help="the clip the bundle was trained on (default: scene.json 'source')")
    parser.add_argument("--out", help="report HTML path (default <bundle>/report/report.html)")


def run(args, reporter):
    from ..report import write_report

    path = write_report(args.bundle, args.out, clip_path=args.clip)
    reporter.result(bundle=str(args.bundle), report=str(path))
    return 0
