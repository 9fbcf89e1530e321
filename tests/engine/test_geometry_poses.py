"""numpy pose math of engine/geometry/poses.py (camera centres, Kabsch rotation)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from engine.geometry.poses import camera_centres, kabsch_rotation


def test_camera_centres_invert_the_extrinsics():
    R = Rotation.random(4, random_state=0).as_matrix()
    C = np.random.default_rng(1).normal(size=(4, 3))
    w2c = np.tile(np.eye(4), (4, 1, 1))
    w2c[:, :3, :3] = R
    w2c[:, :3, 3] = -np.einsum("fij,fj->fi", R, C)
    np.testing.assert_allclose(camera_centres(w2c), C, atol=1e-12)


def test_kabsch_recovers_a_proper_rotation():
    R = Rotation.random(random_state=2).as_matrix()
    u = np.random.default_rng(3).normal(size=(30, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    R2 = kabsch_rotation(u, u @ R.T)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    assert np.isclose(np.linalg.det(kabsch_rotation(u, -u)), 1.0)  # a reflection is never returned
