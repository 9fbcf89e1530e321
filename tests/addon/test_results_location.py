"""Issue #18.4: results survive uninstalling / updating the extension. They go beside the
.blend (or to the preferences' results folder while it is unsaved), named after the clip;
the engine's compiled-kernel cache lives outside the extension's folders."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.addon._support import REPO, bpy, clean_jobs, failing_python, registered, user_dir  # noqa: F401


def _dataset(tmp_path) -> Path:
    folder = tmp_path / "footage" / "cups"
    (folder / "camera").mkdir(parents=True)
    (folder / "dataset.json").write_text("{}", encoding="utf-8")
    return folder


def test_results_beside_the_blend_named_after_the_clip(extension, registered, tmp_path, user_dir, clean_jobs):
    registered.engine_python = str(failing_python(tmp_path))
    s = bpy.context.scene.motion_splats_result
    s.clip_path = str(_dataset(tmp_path))
    blend = tmp_path / "shots" / "shot.blend"
    blend.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    s = bpy.context.scene.motion_splats_result
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}
    job = clean_jobs.latest("train")
    argv = job.process.argv
    bundle = Path(argv[argv.index("--out") + 1])
    assert bundle == blend.parent / "MotionSplats" / "cups"
    assert not bundle.is_relative_to(user_dir)
    # an installed extension's kernel cache: outside the extension (sources and user folder)
    numba = Path(extension.addon.preferences.engine_env(installed=True)["NUMBA_CACHE_DIR"])
    assert not numba.is_relative_to(REPO) and not numba.is_relative_to(user_dir)
    clean_jobs.wait(job, 20)
    bundle.mkdir(parents=True)  # the first run's result exists: a second one never overwrites it
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}
    argv = clean_jobs.latest("train").process.argv
    assert Path(argv[argv.index("--out") + 1]) == blend.parent / "MotionSplats" / "cups-2"


def test_unsaved_file_uses_the_results_folder(extension, registered, tmp_path, user_dir, clean_jobs):
    registered.engine_python = str(failing_python(tmp_path))
    registered.results_dir = str(tmp_path / "my results")
    bpy.context.scene.motion_splats_result.clip_path = str(_dataset(tmp_path))
    assert not bpy.data.filepath
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}
    argv = clean_jobs.latest("train").process.argv
    assert Path(argv[argv.index("--out") + 1]) == tmp_path / "my results" / "cups"


_INSTALL = textwrap.dedent("""
    import bpy, json, os, sys
    zip_path, out = sys.argv[-2], sys.argv[-1]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    repos = bpy.context.preferences.extensions.repos
    idx = [r.module for r in repos].index("user_default")
    def install():
        assert bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                        enable_on_install=True) == {"FINISHED"}
        return sys.modules["bl_ext.user_default.motion_splats"]
    ext = install()
    bundle, manifest = ext.operators.reconstruct_ops.result_paths(bpy.context, "cups.mp4")
    bundle.mkdir(parents=True)
    (bundle / "scene.json").write_text("{}")
    numba = ext.addon.preferences.numba_cache_dir()
    numba.mkdir(parents=True)
    (numba / "kernel.nbi").write_text("x")
    assert bpy.ops.extensions.package_uninstall(repo_index=idx, pkg_id="motion_splats") == {"FINISHED"}
    after_uninstall = (bundle / "scene.json").is_file()
    ext = install()
    again, _ = ext.operators.reconstruct_ops.result_paths(bpy.context, "cups.mp4")
    json.dump({"bundle": str(bundle), "after_uninstall": after_uninstall,
               "after_reinstall": (bundle / "scene.json").is_file(), "next": str(again),
               "numba_kept": (ext.addon.preferences.numba_cache_dir() / "kernel.nbi").is_file()},
              open(out, "w"))
""")


@pytest.mark.slow
def test_uninstall_and_reinstall_keep_results(tmp_path):
    """The real extension installer: install the `make dist` zip, make a result, uninstall,
    reinstall (Blender deletes the extension's user folder on uninstall)."""
    dist = subprocess.run([sys.executable, str(REPO / "tools" / "build_dist.py"), "--out", str(tmp_path / "dist")],
                          capture_output=True, text=True)
    if dist.returncode != 0 and "no Blender extension validator found" in dist.stderr:
        pytest.skip("no Blender extension validator on this machine")
    assert dist.returncode == 0, dist.stderr
    script = tmp_path / "install.py"
    script.write_text(_INSTALL, encoding="utf-8")
    home = tmp_path / "home"
    env = {k: v for k, v in os.environ.items() if k not in ("MOTION_SPLATS_USER_DIR", "XDG_CACHE_HOME",
                                                             "XDG_CONFIG_HOME")}
    env["HOME"] = str(home)
    res = subprocess.run([sys.executable, str(script), dist.stdout.strip(), str(tmp_path / "out.json")],
                         capture_output=True, text=True, env=env, timeout=300, cwd=str(tmp_path))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    import json

    out = json.loads((tmp_path / "out.json").read_text())
    assert Path(out["bundle"]) == home / "MotionSplats" / "cups"
    assert out["after_uninstall"] and out["after_reinstall"] and out["numba_kept"]
    assert Path(out["next"]) == home / "MotionSplats" / "cups-2"  # and a new result does not overwrite it
