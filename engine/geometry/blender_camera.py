"""Blender camera settings <-> pinhole intrinsics, and the numpy versions of the camera
axis conversion and quaternion -> matrix.

No torch: the add-on imports this inside Blender (numpy only, imported lazily by the
array helpers). The torch versions used by the engine live in ``camera.py`` and
``quaternion.py``; tests keep both equal. Reproduces Blender's
viewplane rules (``BKE_camera_params_compute_viewplane``): the sensor fit picks which
image axis the sensor size spans (AUTO: the larger, after pixel aspect), lens shift is
measured in units of that fitted axis, and pixel aspect stretches y.

Pixel coordinates are continuous with y down and the upper-left pixel's centre at
``(0.5, 0.5)``, so a camera without shift has ``cx = W/2, cy = H/2``.
"""

from __future__ import annotations

#: OpenCV camera axes from Blender's (x right; y down vs up; z forward vs backward).
CV_FROM_BLENDER_DIAG = (1.0, -1.0, -1.0, 1.0)


def _fit(sensor_fit: str, res_x: float, res_y: float, aspect_x: float, aspect_y: float) -> str:
    if sensor_fit == "AUTO":
        return "HORIZONTAL" if aspect_x * res_x >= aspect_y * res_y else "VERTICAL"
    if sensor_fit not in ("HORIZONTAL", "VERTICAL"):
        raise ValueError(f"unknown sensor_fit {sensor_fit!r}")
    return sensor_fit


def blender_camera_intrinsics(lens_mm: float, sensor_width_mm: float, sensor_height_mm: float,
                              sensor_fit: str, shift_x: float, shift_y: float, res_x: int, res_y: int,
                              pixel_aspect_x: float = 1.0, pixel_aspect_y: float = 1.0,
                              resolution_percentage: int = 100):
    """Pinhole intrinsics of a Blender perspective camera.

    Returns
    -------
    (fx, fy, cx, cy, width, height) in pixels of the rendered image.
    """
    width = int(res_x * resolution_percentage / 100)
    height = int(res_y * resolution_percentage / 100)
    ycor = pixel_aspect_y / pixel_aspect_x
    fit = _fit(sensor_fit, width, height, pixel_aspect_x, pixel_aspect_y)
    sensor = sensor_height_mm if sensor_fit == "VERTICAL" else sensor_width_mm
    viewfac = width if fit == "HORIZONTAL" else ycor * height
    fx = lens_mm / sensor * viewfac
    fy = fx / ycor
    cx = 0.5 * width - shift_x * viewfac
    cy = 0.5 * height + shift_y * viewfac / ycor
    return fx, fy, cx, cy, width, height


def blender_camera_from_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                                   sensor_width_mm: float = 36.0) -> dict:
    """Blender camera settings that reproduce the given intrinsics exactly.

    Uses a HORIZONTAL sensor fit of ``sensor_width_mm`` and encodes ``fy ≠ fx`` as pixel
    aspect. Returns keys ``lens, sensor_width, sensor_height, sensor_fit, shift_x,
    shift_y, pixel_aspect_x, pixel_aspect_y, res_x, res_y``.
    """
    ycor = fx / fy  # pixel_aspect_y / pixel_aspect_x
    aspect_x, aspect_y = (1.0, ycor) if ycor >= 1.0 else (1.0 / ycor, 1.0)
    viewfac = float(width)
    return {
        "lens": fx * sensor_width_mm / viewfac,
        "sensor_width": sensor_width_mm,
        "sensor_height": sensor_width_mm * height / width,
        "sensor_fit": "HORIZONTAL",
        "shift_x": (0.5 * width - cx) / viewfac,
        "shift_y": (cy - 0.5 * height) * ycor / viewfac,
        "pixel_aspect_x": aspect_x,
        "pixel_aspect_y": aspect_y,
        "res_x": int(width),
        "res_y": int(height),
    }


# -- numpy helpers (the add-on's side of camera.py / quaternion.py) --------------------------
def w2c_from_blender_matrix(matrix_world):
    """OpenCV ``w2c [..., 4, 4]`` of Blender camera-to-world matrices ``[..., 4, 4]``
    (object scale removed), numpy float64."""
    import numpy as np

    m = np.array(matrix_world, dtype=np.float64)
    m[..., :3, :3] /= np.linalg.norm(m[..., :3, :3], axis=-2, keepdims=True)
    return np.diag(CV_FROM_BLENDER_DIAG) @ np.linalg.inv(m)


def blender_matrix_from_w2c(w2c):
    """Blender camera ``matrix_world [..., 4, 4]`` from OpenCV ``w2c [..., 4, 4]`` (numpy)."""
    import numpy as np

    return np.linalg.inv(np.diag(CV_FROM_BLENDER_DIAG) @ np.asarray(w2c, dtype=np.float64))


def quat_to_matrix_np(q):
    """Rotation matrices ``[..., 3, 3]`` of quaternions ``q [..., 4]`` (w, x, y, z;
    normalised here), numpy float64."""
    import numpy as np

    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
