"""``make demo``: the whole product on the bundled clip, end to end.

    .venv/bin/python tools/demo.py [--clip data/demo_clip] [--out out/demo]
                                   [--max-frames N] [--steps N] [--render-frames 1,16,32]

1. Engine (a subprocess, progress on the terminal): cameras from the clip -> priors ->
   MANI nodes -> Hermite splines -> training at the ``preview`` preset -> held-out eval.
2. Blender (bpy in this process, through the add-on's own code): Empties with
   F-curves, the dual-quaternion rig, the Gaussian preview, camera and footage ->
   ``out/demo/demo.blend``.
3. Renders the same frames with Cycles and with the engine, side by side, and writes
   ``out/demo/report.html``.

Earlier demo output in ``--out`` is replaced (it is the demo's own folder); nothing
else is touched.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _say(msg: str) -> None:
    print(f"\n==> {msg}", flush=True)


def run_engine(args: list[str], jsonl: bool = False) -> dict | None:
    """Run ``python -m engine ...`` with live progress; return its result event."""
    cmd = [sys.executable, "-m", "engine", *map(str, args)]
    if not jsonl:
        subprocess.run(cmd, cwd=REPO, check=True)
        return None
    proc = subprocess.run(cmd + ["--jsonl"], cwd=REPO, stdout=subprocess.PIPE, text=True)
    from engine.protocol import parse_event

    events = [e for e in map(parse_event, proc.stdout.splitlines()) if e]
    if proc.returncode != 0 or not events or events[-1]["event"] != "result":
        err = next((e for e in reversed(events) if e["event"] == "error"), None)
        raise SystemExit(f"engine {args[0]} failed: {err['message'] if err else proc.returncode}")
    return events[-1]


def compare(engine_dir: Path, cycles: list[str]) -> list[dict]:
    """PSNR between the Cycles render and the engine's own render of the same frame."""
    from engine.bench.cycles import psnr_files

    rows = []
    for c in cycles:
        psnr = psnr_files(c, engine_dir / Path(c).name)
        if psnr is not None:
            rows.append({"frame": Path(c).stem, "psnr_cycles_vs_engine": psnr})
    return rows


def append_cycles_section(report: Path, comparison: list[dict], cycles: list[str], engine_dir: Path) -> None:
    """Add the Cycles-vs-engine side-by-side frames to the run report (atomic rewrite)."""
    import html
    import os

    from engine.fsutil import atomic_write_text

    rows = []
    by_frame = {r["frame"]: r["psnr_cycles_vs_engine"] for r in comparison}
    for c in cycles:
        name = Path(c).stem
        e = engine_dir / Path(c).name
        rel_c = os.path.relpath(c, report.parent)
        rel_e = os.path.relpath(e, report.parent)
        psnr = by_frame.get(name)
        rows.append(f"<tr><td>{html.escape(name)}</td><td><img src='{html.escape(rel_c)}' width=320></td>"
                    f"<td><img src='{html.escape(rel_e)}' width=320></td>"
                    f"<td>{'-' if psnr is None else f'{psnr:.2f} dB'}</td></tr>")
    section = ("<h2>Blender (Cycles) vs engine</h2><p>The same trained frame rendered by Cycles from the "
               "add-on's Gaussian preview (ellipsoid mode) and by the engine's rasteriser.</p>"
               "<table><tr><th>frame</th><th>Cycles</th><th>engine</th><th>PSNR</th></tr>"
               + "".join(rows) + "</table>")
    text = report.read_text(encoding="utf-8")
    text = text.replace("</body>", section + "</body>") if "</body>" in text else text + section
    atomic_write_text(report, text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clip", type=Path, default=REPO / "data" / "demo_clip")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "demo")
    parser.add_argument("--max-frames", type=int, default=None, help="truncate the clip (tests use a few frames)")
    parser.add_argument("--steps", type=int, default=None, help="training steps (default: the preview preset's)")
    parser.add_argument("--render-frames", default="1,16,32", help="frames rendered by Cycles and the engine")
    parser.add_argument("--cycles-samples", type=int, default=16)
    args = parser.parse_args(argv)
    t0 = time.time()
    out = args.out.resolve()
    if out.exists():
        shutil.rmtree(out)  # the demo's own output folder, rebuilt every run
    out.mkdir(parents=True)
    bundle = out / "bundle"
    sys.path.insert(0, str(REPO))

    _say("1/4  engine: priors -> MANI nodes -> splines -> training (preview preset)")
    train_args = ["train", args.clip, "--out", bundle, "--preset", "preview"]
    if args.max_frames:
        train_args += ["--max-frames", args.max_frames]
    if args.steps:
        train_args += ["--steps", args.steps]
    run_engine(train_args)
    scene = json.loads((bundle / "scene.json").read_text())
    stats = scene["stats"]
    frame_end = int(scene["time"]["frame_end"])
    frames = sorted({min(max(int(f), 1), frame_end) for f in args.render_frames.split(",")})

    _say("2/4  engine: held-out evaluation and renders")
    engine_dir = out / "engine"
    run_engine(["render", bundle, "--frames", ",".join(map(str, frames)), "--out", engine_dir, "--quiet"])

    _say("3/4  Blender: Empties + F-curves, rig, Gaussian preview -> demo.blend; Cycles renders")
    blend = out / "demo.blend"
    from tools.bpy_scene import render_cycles  # the bpy half, shared with `engine.bench cycles`

    blender = render_cycles(bundle, frames, out / "cycles", args.cycles_samples, blend_path=blend)
    comparison = compare(engine_dir, blender["cycles"])

    _say("4/4  report")
    from engine.report import write_report

    report = write_report(bundle, out / "report.html", clip_path=args.clip)
    append_cycles_section(report, comparison, blender["cycles"], engine_dir)
    summary = {
        "bundle": str(bundle), "blend": str(blend), "report": str(report),
        "held_out": stats.get("eval"), "held_out_initial": stats.get("eval_init"),
        "cycles_vs_engine": comparison, "minutes": round((time.time() - t0) / 60, 1),
    }
    print(json.dumps(summary, indent=2))
    _say(f"done in {summary['minutes']} min. Open {blend} in Blender, or {report} in a browser.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
