"""The report's camera-path section (issue #21): the path drawn from scene.json and the solve's choice."""

from __future__ import annotations

import re

import numpy as np

from engine.io import solve_select as sel
from engine.report_camera import camera_path_section, camera_path_svg


def _w2c(C):
    w2c = np.tile(np.eye(4), (len(C), 1, 1))
    w2c[:, :3, 3] = -np.asarray(C, float)
    return w2c


def _circles(svg):
    return [(float(x), float(y)) for x, y in re.findall(r'<circle cx="([-\d.]+)" cy="([-\d.]+)"', svg)]


def test_path_svg_places_cameras_along_their_path():
    C = np.c_[np.linspace(0, 2, 5), np.zeros(5), np.linspace(0, 1, 5)]  # a straight line, evenly spaced
    pts = np.array(_circles(camera_path_svg(_w2c(C), np.linspace(0, 1, 5))))
    assert len(pts) == 5
    gaps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert gaps.min() > 10 and np.allclose(gaps, gaps[0], atol=0.2)  # even spacing survives the projection
    assert "path length 2.24" in camera_path_svg(_w2c(C), np.linspace(0, 1, 5))


def test_fixed_centre_is_one_point_and_section_states_the_choice():
    from scipy.spatial.transform import Rotation

    F = 6
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[:, :3, :3] = Rotation.from_euler("y", np.linspace(0, 20, F)[:, None], degrees=True).as_matrix()
    info = {"model": "rotation", "registered": np.ones(F, bool), "num_registered": F, "mean_reproj_error": 0.4,
            "num_points": 0, "reason": "a homography leaves 0.02 px of parallax <on> the static matches",
            "parallax_px": 0.02, "parallax_floor_px": 0.07, "fov_deg": 60.0, "max_rotation_deg": 20.0,
            "rejected": []}
    scene = {"cameras": [{"w2c": m.tolist(), "time": t} for m, t in zip(w2c, np.linspace(0, 1, F))],
             "camera_solve": sel.summary(info)}
    html_out = camera_path_section(scene)
    pts = np.array(_circles(html_out))
    assert len(pts) == F and np.ptp(pts, axis=0).max() < 1e-6
    assert "rotation" in html_out and "&lt;on&gt;" in html_out and "0.02" in html_out
    assert "Cameras came with the clip" in camera_path_section({"cameras": scene["cameras"]})
