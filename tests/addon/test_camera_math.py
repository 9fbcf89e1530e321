"""Issue #19 (add-on side): the add-on's camera axis conversion and quaternion -> matrix are
the engine's numpy helpers (engine/geometry/blender_camera.py), equal to the engine's torch
versions, and there is one animated-camera builder."""

from __future__ import annotations

import inspect

import numpy as np
import torch

from engine.geometry import blender_camera as bc
from engine.geometry import camera, quaternion


def test_numpy_helpers_match_the_torch_ones():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(20, 4))
    np.testing.assert_allclose(bc.quat_to_matrix_np(q),
                               quaternion.quat_to_matrix(quaternion.quat_normalize(torch.from_numpy(q))).numpy(),
                               atol=1e-12)
    R = bc.quat_to_matrix_np(q)
    w2c = np.tile(np.eye(4), (20, 1, 1))
    w2c[:, :3, :3], w2c[:, :3, 3] = R, rng.normal(size=(20, 3))
    mw = bc.blender_matrix_from_w2c(w2c)
    np.testing.assert_allclose(mw, camera.blender_matrix_world_from_w2c_opencv(torch.from_numpy(w2c)).numpy(),
                               atol=1e-12)
    scaled = mw.copy()
    scaled[:, :3, :3] *= 2.5  # object scale does not change the camera
    np.testing.assert_allclose(bc.w2c_from_blender_matrix(scaled), w2c, atol=1e-12)


def test_addon_has_no_copy_of_the_camera_math(extension):
    build, cameras, exporters = extension.addon.build, extension.addon.cameras, extension.addon.exporters
    geo = extension.engine.geometry.blender_camera
    assert build.quat_to_matrix is geo.quat_to_matrix_np and cameras.qvec_to_matrix is geo.quat_to_matrix_np
    assert cameras.w2c_from_blender_matrix is geo.w2c_from_blender_matrix
    for module in (build, cameras, exporters):
        src = inspect.getsource(module)
        assert "CV_FROM_BLENDER =" not in src and "1 - 2 * (y * y + z * z)" not in src, module.__name__
    # one animated-camera builder: build_camera delegates to cameras.build_animated_camera
    assert "build_animated_camera" in inspect.getsource(build.build_camera)
    assert "keyframe_insert" not in inspect.getsource(build)
