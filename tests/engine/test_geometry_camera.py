"""Cameras (engine/geometry/camera.py) and Blender camera intrinsics (blender_camera.py, checked against bpy)."""

import numpy as np
import pytest
import torch

from engine.geometry import camera
from engine.geometry.blender_camera import blender_camera_from_intrinsics, blender_camera_intrinsics

DTYPES = [torch.float32, torch.float64]


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("with_dist", [False, True])
def test_project_unproject_round_trip(dtype, with_dist):
    g = torch.Generator().manual_seed(0)
    K = camera.intrinsics(300.0, 310.0, 160.3, 119.7, dtype=dtype)
    w2c = camera.look_at(torch.tensor([3.0, -4.0, 1.5], dtype=dtype), torch.zeros(3, dtype=dtype))
    x = torch.randn(500, 3, generator=g, dtype=dtype) * 0.5
    dist = torch.tensor([-0.12, 0.03, 0.001, -0.002, 0.0], dtype=dtype) if with_dist else None
    uv, z = camera.project(K, w2c, x, dist)
    assert (z > 0).all()
    back = camera.unproject(K, w2c, uv, z, dist)
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(back, x, atol=tol, rtol=0)


def test_look_at_is_opencv_and_blender_conversion_round_trips():
    eye = torch.tensor([0.0, -5.0, 0.0], dtype=torch.float64)
    w2c = camera.look_at(eye, torch.zeros(3, dtype=torch.float64))
    K = camera.intrinsics(100, 100, 50, 50)
    uv, z = camera.project(K, w2c, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert float(z[0]) == pytest.approx(5.0) and float(uv[0, 1]) < 50  # world up is image up (smaller v)
    M = camera.blender_matrix_world_from_w2c_opencv(w2c)
    torch.testing.assert_close(camera.w2c_opencv_from_blender_matrix_world(M), w2c)
    # a Blender camera looks down its local -z
    forward = -M[:3, 2]
    torch.testing.assert_close(forward, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def _bpy_uv(bpy, scene, cam, points, w, h):
    """Pixel coordinates (continuous, y down) of world points as Blender projects them."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    bpy.context.view_layer.update()
    out = []
    for p in points:
        ndc = world_to_camera_view(scene, cam, Vector(p.tolist()))
        out.append((ndc.x * w, (1 - ndc.y) * h))
    return np.array(out)


@pytest.mark.parametrize("fit,res,shift,aspect,pct", [
    ("AUTO", (640, 360), (0.0, 0.0), (1.0, 1.0), 100),
    ("AUTO", (300, 500), (0.1, -0.05), (1.0, 1.0), 100),
    ("HORIZONTAL", (400, 300), (-0.2, 0.1), (1.0, 1.0), 50),
    ("VERTICAL", (400, 300), (0.05, 0.2), (1.0, 1.0), 100),
    ("AUTO", (400, 300), (0.1, 0.1), (2.0, 1.0), 100),
    ("AUTO", (300, 400), (-0.1, 0.15), (1.0, 3.0), 100),
    ("VERTICAL", (320, 480), (0.0, 0.1), (1.0, 1.5), 75),
])
def test_blender_camera_intrinsics_match_blender(fit, res, shift, aspect, pct):
    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("cam")
    cam_data.lens, cam_data.sensor_width, cam_data.sensor_height = 35.0, 36.0, 24.0
    cam_data.sensor_fit = fit
    cam_data.shift_x, cam_data.shift_y = shift
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.location = (0.3, -4.0, 1.0)
    cam.rotation_euler = (1.3, 0.1, 0.2)
    scene.render.resolution_x, scene.render.resolution_y = res
    scene.render.resolution_percentage = pct
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    bpy.context.view_layer.update()
    fx, fy, cx, cy, w, h = blender_camera_intrinsics(cam_data.lens, 36.0, 24.0, fit, shift[0], shift[1], res[0],
                                                     res[1], aspect[0], aspect[1], pct)
    assert (w, h) == (res[0] * pct // 100, res[1] * pct // 100)
    K = camera.intrinsics(fx, fy, cx, cy)
    M = torch.tensor([list(r) for r in cam.matrix_world], dtype=torch.float64)
    w2c = camera.w2c_opencv_from_blender_matrix_world(M)
    pts = np.random.default_rng(0).normal(size=(8, 3)) * 0.7
    expect = _bpy_uv(bpy, scene, cam, pts, w, h)
    for dtype, tol in ((torch.float64, 1e-3), (torch.float32, 2e-2)):
        uv, _ = camera.project(K.to(dtype), w2c.to(dtype), torch.tensor(pts, dtype=dtype))
        np.testing.assert_allclose(uv.double().numpy(), expect, atol=tol)
    # and back again
    settings_ = blender_camera_from_intrinsics(fx, fy, cx, cy, w, h)
    again = blender_camera_intrinsics(settings_["lens"], settings_["sensor_width"], settings_["sensor_height"],
                                      settings_["sensor_fit"], settings_["shift_x"], settings_["shift_y"],
                                      settings_["res_x"], settings_["res_y"], settings_["pixel_aspect_x"],
                                      settings_["pixel_aspect_y"])
    np.testing.assert_allclose(again, (fx, fy, cx, cy, w, h), atol=1e-9)
    # the inverse's settings, applied to the Blender camera, project the same way
    cam_data.lens, cam_data.sensor_width = settings_["lens"], settings_["sensor_width"]
    cam_data.sensor_height, cam_data.sensor_fit = settings_["sensor_height"], settings_["sensor_fit"]
    cam_data.shift_x, cam_data.shift_y = settings_["shift_x"], settings_["shift_y"]
    scene.render.resolution_x, scene.render.resolution_y = settings_["res_x"], settings_["res_y"]
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = settings_["pixel_aspect_x"]
    scene.render.pixel_aspect_y = settings_["pixel_aspect_y"]
    np.testing.assert_allclose(_bpy_uv(bpy, scene, cam, pts, w, h), expect, atol=1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_camera_on_device(device):
    dtype = torch.float32
    K = camera.intrinsics(200.0, 200.0, 64.0, 48.0, dtype=dtype).to(device)
    w2c = camera.look_at(torch.tensor([0.0, -3.0, 0.5], device=device), torch.zeros(3, device=device))
    dist = torch.tensor([-0.05, 0.01, 0.0005, 0.0, 0.0], device=device)
    x = torch.randn(100, 3, generator=torch.Generator().manual_seed(2)).mul(0.3).to(device)
    uv, z = camera.project(K, w2c, x, dist)
    assert uv.device.type == device
    torch.testing.assert_close(camera.unproject(K, w2c, uv, z, dist), x, atol=1e-4, rtol=0)
