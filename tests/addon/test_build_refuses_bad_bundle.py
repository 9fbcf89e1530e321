"""A bundle with a broken camera or NaN appearance is refused before anything is built (#22.7)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bpy

from engine import bundle as bio

from tests.addon.test_build_bundle import make_bundle


def _singular_camera(path):
    scene = json.loads((path / "scene.json").read_text())
    scene["cameras"][1]["w2c"] = np.diag([1.0, 1.0, 0.0, 1.0]).tolist()
    (path / "scene.json").write_text(json.dumps(scene))


def _nan_opacity(path):
    g = bio.read_ply(path / "gaussians.ply")
    op = g.opacity_logits.copy()
    op[5] = np.nan
    bio.write_ply(path / "gaussians.ply", bio.GaussianArrays(means=g.means, quats=g.quats, log_scales=g.log_scales,
                                                             opacity_logits=op, sh=g.sh))


@pytest.mark.parametrize("breaks,needle", [(_singular_camera, "w2c"), (_nan_opacity, "opacity")])
def test_broken_bundle_builds_nothing(extension, empty_scene, tmp_path, breaks, needle):
    make_bundle(tmp_path / "bundle")
    breaks(tmp_path / "bundle")
    objects, collections = len(bpy.data.objects), len(bpy.data.collections)
    # the extension's own copy of the engine raises its own InputError class
    with pytest.raises(extension.engine.errors.InputError, match=needle):
        extension.addon.build.build_bundle_into_scene(bpy.context, tmp_path / "bundle")
    assert len(bpy.data.objects) == objects and len(bpy.data.collections) == collections
