"""The Blender (bpy) half of ``make demo`` and of the ``build`` / ``cycles`` benches.

``engine/`` never imports bpy, so the benches run this script with the same interpreter
(the venv has the ``bpy`` module) and read the one JSON line it prints last::

    python tools/bpy_scene.py build BUNDLE [--preview POINTS|ELLIPSOIDS] [--density 1] [--eval-frame]
    python tools/bpy_scene.py cycles BUNDLE --frames 1,16,32 --out DIR [--samples 16] [--blend FILE]

``build`` times ``addon.build.build_bundle_into_scene`` (Empties + F-curves, rig,
Gaussian mesh + attributes, preview modifier, camera) with its per-part breakdown;
``--eval-frame`` also times the first depsgraph evaluation of a frame (rig + preview).
``cycles`` builds the ellipsoid preview, optionally saves the .blend, and renders the
frames with Cycles on the CPU into ``DIR/frame_<n>.png``.

Everything goes through the add-on's own code, imported as the package ``motion_splats``
like Blender imports an installed extension.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def import_extension():
    """The repo imported as the add-on package ``motion_splats`` (as Blender would)."""
    if "motion_splats" in sys.modules:
        return sys.modules["motion_splats"]
    root = Path(tempfile.mkdtemp(prefix="ms_ext_"))
    # removed when the process ends (rmtree unlinks the symlink, it does not follow it)
    atexit.register(shutil.rmtree, root, ignore_errors=True)
    (root / "motion_splats").symlink_to(REPO, target_is_directory=True)
    sys.path.insert(0, str(root))
    return importlib.import_module("motion_splats")


def build_scene(bundle_dir, preview: str = "POINTS", density: float = 1.0, eval_frame: bool = False) -> dict:
    """A fresh scene with ``bundle_dir`` built into it; returns counts and timings (s).

    The add-on stays registered (the caller may render or save); call
    ``import_extension().unregister()`` when done.
    """
    import bpy

    ext = import_extension()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ext.register()
    t0 = time.perf_counter()
    info = ext.addon.build.build_bundle_into_scene(bpy.context, str(bundle_dir), preview=preview, density=density)
    wall = time.perf_counter() - t0
    res = {"nodes": len(info["empties"]), "gaussians": info["gaussians"],
           "keys": 0 if info["key_frames"] is None else int(len(info["key_frames"])), "preview": preview,
           "density": density, "timings": {k: round(v, 4) for k, v in info["timings"].items()},
           "build_s": round(wall, 4)}
    if eval_frame:
        scene = bpy.context.scene
        t0 = time.perf_counter()
        scene.frame_set((scene.frame_start + scene.frame_end) // 2)
        bpy.context.evaluated_depsgraph_get()
        res["eval_frame_s"] = round(time.perf_counter() - t0, 4)
    return res


def render_cycles(bundle_dir, frames, out_dir, samples: int = 16, blend_path=None) -> dict:
    """Build the ellipsoid preview, save ``blend_path`` (atomic), render ``frames`` with Cycles."""
    import bpy

    ext = import_extension()
    info = build_scene(bundle_dir, preview="ELLIPSOIDS")
    try:
        scene = bpy.context.scene
        col = next(c for c in bpy.data.collections if "ms_bundle" in c)
        ext.addon.render_setup.setup_render(bpy.context, col)  # camera, resolution, colour management
        scene.render.engine = "CYCLES"
        scene.cycles.samples = samples
        scene.cycles.use_denoising = False
        scene.cycles.device = "CPU"
        if blend_path:
            blend_path = Path(blend_path)
            tmp_blend = blend_path.with_suffix(".tmp.blend")
            bpy.ops.wm.save_as_mainfile(filepath=str(tmp_blend), copy=True)
            tmp_blend.replace(blend_path)
        renders, seconds = [], []
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        for f in frames:
            scene.frame_set(int(f))
            target = out_dir / f"frame_{int(f):05d}.png"
            scene.render.filepath = str(target)
            t0 = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            seconds.append(round(time.perf_counter() - t0, 3))
            renders.append(str(target))
    finally:
        ext.unregister()
    return {"build": info, "cycles": renders, "render_s": seconds, "samples": samples,
            "width": scene.render.resolution_x, "height": scene.render.resolution_y}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="time building a bundle into a fresh scene")
    b.add_argument("bundle")
    b.add_argument("--preview", default="POINTS", choices=("POINTS", "ELLIPSOIDS"))
    b.add_argument("--density", type=float, default=1.0)
    b.add_argument("--eval-frame", action="store_true", help="also time the first evaluation of a frame")
    c = sub.add_parser("cycles", help="build the ellipsoid preview and render frames with Cycles")
    c.add_argument("bundle")
    c.add_argument("--frames", required=True, help="comma-separated scene frames")
    c.add_argument("--out", required=True, help="folder for frame_<n>.png")
    c.add_argument("--samples", type=int, default=16)
    c.add_argument("--blend", help="also save the scene to this .blend")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(REPO))
    if args.cmd == "build":
        res = build_scene(args.bundle, args.preview, args.density, args.eval_frame)
        import_extension().unregister()
    else:
        frames = [int(f) for f in args.frames.split(",") if f.strip()]
        res = render_cycles(args.bundle, frames, args.out, args.samples, args.blend)
    print(json.dumps(res), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
