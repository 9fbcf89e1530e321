"""Blender camera settings <-> pinhole intrinsics, in pure Python.

No numpy or torch: the add-on imports this inside Blender. Reproduces Blender's
viewplane rules (``BKE_camera_params_compute_viewplane``): the sensor fit picks which
image axis the sensor size spans (AUTO: the larger, after pixel aspect), lens shift is
measured in units of that fitted axis, and pixel aspect stretches y.

Pixel coordinates are continuous with y down and the upper-left pixel's centre at
``(0.5, 0.5)``, so a camera without shift has ``cx = W/2, cy = H/2``.
"""

from __future__ import annotations


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
