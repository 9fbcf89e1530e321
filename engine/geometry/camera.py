"""Pinhole cameras: projection, back-projection, distortion and axis conventions.

Conventions (``docs/architecture.md``): OpenCV camera axes (x right, y down, z forward),
``w2c [..., 4, 4]`` world-to-camera, ``K [..., 3, 3]`` in *continuous* pixel
coordinates (the upper-left pixel's centre is ``(0.5, 0.5)``, as in COLMAP and gsplat).
Distortion uses OpenCV's Brown–Conrady model ``dist = (k1, k2, p1, p2, k3)`` applied to
normalised camera coordinates.
"""

from __future__ import annotations

import dataclasses

import torch

#: Camera-space axis flip between Blender/OpenGL (y up, looking down −z) and OpenCV.
OPENCV_FROM_BLENDER = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))


def world_to_camera(w2c: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Points ``x [..., 3]`` in world -> camera coordinates (``w2c [..., 4, 4]``)."""
    return (w2c[..., :3, :3] @ x.unsqueeze(-1)).squeeze(-1) + w2c[..., :3, 3]


def camera_to_world(w2c: torch.Tensor, x_cam: torch.Tensor) -> torch.Tensor:
    """Camera coordinates ``[..., 3]`` -> world, inverting the rigid ``w2c``."""
    R = w2c[..., :3, :3]
    return (R.transpose(-1, -2) @ (x_cam - w2c[..., :3, 3]).unsqueeze(-1)).squeeze(-1)


def camera_centers(w2c: torch.Tensor) -> torch.Tensor:
    """Camera centres ``[..., 3]`` in world: ``−Rᵀ t``."""
    R = w2c[..., :3, :3]
    return -(R.transpose(-1, -2) @ w2c[..., :3, 3].unsqueeze(-1)).squeeze(-1)


def ray_parallax_sin(points: torch.Tensor, origins: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Sine of the angle ``[P]`` at each of ``points [P, 3]`` between the ray from its own
    ``origins [P, 3]`` and the ray from ``center [3]`` (0 when they are one line; either ray
    of zero length counts as 0). How far a point seen from ``origins`` may move in the view
    from ``center`` when its depth along the first ray is uncertain: a depth error ``e``
    shifts it by about ``e sin(angle)`` across the second ray."""
    a = points - origins
    b = points - center
    cross = torch.linalg.cross(a, b, dim=-1).norm(dim=-1)
    return cross / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-20)


#: camera centres within this fraction of the scene extent of each other: a camera that does not translate
FIXED_CAMERA_TOL = 1e-4


def camera_translates(w2c: torch.Tensor, extent: float) -> bool:
    """Whether the camera centres of ``w2c [F, 4, 4]`` move by more than
    :data:`FIXED_CAMERA_TOL` of the scene ``extent`` (a tripod or a rotation-only solve: no)."""
    centres = camera_centers(w2c)
    spread = (centres - centres.mean(0)).norm(dim=1).max()
    return bool(spread > FIXED_CAMERA_TOL * max(float(extent), 1e-12))


def scene_extent(w2c, depth=None) -> float:
    """A robust scene radius: the camera centres' spread plus the median positive scene
    depth (1 without one). ``w2c [F, 4, 4]``, ``depth [F, H, W]``: numpy arrays."""
    import numpy as np

    centres = camera_centers(torch.as_tensor(np.asarray(w2c), dtype=torch.float64)).numpy()
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) if len(centres) > 1 else 0.0
    d = None if depth is None else np.asarray(depth)
    med = float(np.median(d[d > 0])) if d is not None and (d > 0).any() else 1.0  # numpy's median: the mean of the middle two
    return max(spread + med, 1e-3)


def invert_rigid(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid ``[..., 4, 4]`` transforms."""
    out = torch.zeros_like(T)
    R = T[..., :3, :3].transpose(-1, -2)
    out[..., :3, :3] = R
    out[..., :3, 3] = -(R @ T[..., :3, 3].unsqueeze(-1)).squeeze(-1)
    out[..., 3, 3] = 1
    return out


def distort(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Apply ``dist (k1, k2, p1, p2, k3)`` to normalised coordinates ``xy [..., 2]``."""
    k1, k2, p1, p2, k3 = dist.to(xy.dtype).unbind(-1)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def undistort(xy_d: torch.Tensor, dist: torch.Tensor, iterations: int = 20) -> torch.Tensor:
    """Invert :func:`distort` by fixed-point iteration (as OpenCV's undistortPoints).

    Converges for the moderate distortion of real lenses (|k1| ≲ 0.5 inside the image).
    """
    k1, k2, p1, p2, k3 = dist.to(xy_d.dtype).unbind(-1)
    xy = xy_d
    for _ in range(iterations):  # fixed small count; vectorised over all points
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        xy = torch.stack([(xy_d[..., 0] - dx) / radial, (xy_d[..., 1] - dy) / radial], dim=-1)
    return xy


def project(K: torch.Tensor, w2c: torch.Tensor, x: torch.Tensor, dist: torch.Tensor | None = None):
    """Project world points to pixels.

    Parameters
    ----------
    K : (..., 3, 3), w2c : (..., 4, 4), x : (..., 3), dist : (..., 5) or None.

    Returns
    -------
    uv : (..., 2) continuous pixel coordinates.
    depth : (...) camera z (negative/zero behind the camera; ``uv`` is then meaningless).
    """
    cam = world_to_camera(w2c, x)
    z = cam[..., 2]
    safe = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    xy = cam[..., :2] / safe.unsqueeze(-1)
    if dist is not None:
        xy = distort(xy, dist)
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return torch.stack([u, v], dim=-1), z


def unproject(K: torch.Tensor, w2c: torch.Tensor, uv: torch.Tensor, depth: torch.Tensor,
              dist: torch.Tensor | None = None) -> torch.Tensor:
    """Back-project pixels ``uv [..., 2]`` with camera z ``depth [...]`` to world ``[..., 3]``."""
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    xy = torch.stack([x, y], dim=-1)
    if dist is not None:
        xy = undistort(xy, dist)
    cam = torch.cat([xy * depth.unsqueeze(-1), depth.unsqueeze(-1)], dim=-1)
    return camera_to_world(w2c, cam)


def w2c_opencv_from_blender_matrix_world(matrix_world: torch.Tensor) -> torch.Tensor:
    """A Blender camera's ``matrix_world [..., 4, 4]`` (no scale) -> OpenCV ``w2c``."""
    flip = torch.eye(4, dtype=matrix_world.dtype, device=matrix_world.device)
    flip[:3, :3] = OPENCV_FROM_BLENDER.to(matrix_world)
    return flip @ invert_rigid(matrix_world)


def blender_matrix_world_from_w2c_opencv(w2c: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`w2c_opencv_from_blender_matrix_world`."""
    flip = torch.eye(4, dtype=w2c.dtype, device=w2c.device)
    flip[:3, :3] = OPENCV_FROM_BLENDER.to(w2c)
    return invert_rigid(flip @ w2c)


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor | None = None) -> torch.Tensor:
    """OpenCV ``w2c [4, 4]`` of a camera at ``eye`` looking at ``target`` (world up = +z)."""
    dtype, device = eye.dtype, eye.device
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device) if up is None else up.to(eye)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-8:  # looking along up: pick another up
        x = torch.linalg.cross(z, torch.tensor([0.0, 1.0, 0.0], dtype=dtype, device=device))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)  # y points down in the image
    R = torch.stack([x, y, z], dim=0)
    w2c = torch.eye(4, dtype=dtype, device=device)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def intrinsics(fx: float, fy: float, cx: float, cy: float, dtype=torch.float64) -> torch.Tensor:
    """``K [3, 3]`` from focal lengths and principal point (pixels)."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


@dataclasses.dataclass
class Camera:
    """One camera: ``K [3, 3]``, ``w2c [4, 4]``, image size, optional distortion and time."""

    K: torch.Tensor
    w2c: torch.Tensor
    width: int
    height: int
    dist: torch.Tensor | None = None
    time: float = 0.0

    def project(self, x):
        return project(self.K, self.w2c, x, self.dist)

    def unproject(self, uv, depth):
        return unproject(self.K, self.w2c, uv, depth, self.dist)

    @property
    def center(self) -> torch.Tensor:
        return camera_centers(self.w2c)
