"""Regenerate the bundled demo clip ``data/demo_clip`` from the project's Blender scene.

    .venv/bin/python tools/make_demo_clip.py [--out data/demo_clip] [--force]

The clip is rendered by ``tools/synth_scene.py`` (Cycles, CPU): a textured room with a
rigid cube, an articulated arm and a waving flag, filmed by a moving camera, with a
rigidly offset second camera for held-out evaluation. Only what the engine reads is
kept (Nerfies/HyperNeRF vrig layout: dataset.json, metadata.json, scene.json, camera/,
rgb/1x/), so the clip stays a few MB. The images are our own renders (project licence).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

FRAMES, WIDTH, HEIGHT, SEED = 32, 160, 120, 7
KEEP = ("dataset.json", "metadata.json", "scene.json", "camera", "rgb/1x")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "data" / "demo_clip")
    parser.add_argument("--force", action="store_true", help="replace an existing clip")
    args = parser.parse_args(argv)
    if args.out.exists() and not args.force:
        print(f"{args.out} exists; pass --force to regenerate it", file=sys.stderr)
        return 2
    from tools.synth_scene import generate_scene

    with tempfile.TemporaryDirectory() as tmp:
        scene = generate_scene(Path(tmp) / "scene", preset="small", frames=FRAMES, width=WIDTH, height=HEIGHT,
                               seed=SEED)
        staging = args.out.with_name(args.out.name + ".tmp")
        shutil.rmtree(staging, ignore_errors=True)
        for item in KEEP:
            src = scene / item
            dst = staging / item
            dst.parent.mkdir(parents=True, exist_ok=True)
            if src.is_dir():
                shutil.copytree(src, dst)
            else:
                shutil.copy2(src, dst)
        (staging / "README.md").write_text(
            "# Motion Splats demo clip\n\n"
            f"{FRAMES} frames at {WIDTH}x{HEIGHT}, rendered by `tools/make_demo_clip.py` "
            "(Blender scene from `tools/synth_scene.py`, seed "
            f"{SEED}) in the Nerfies/HyperNeRF vrig layout: `left_*` frames train, `right_*` frames "
            "(a rigidly offset camera) are held out. Same licence as the project.\n")
        if args.out.exists():
            shutil.rmtree(args.out)
        staging.replace(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
