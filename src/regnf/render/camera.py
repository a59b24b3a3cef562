"""Pinhole cameras posed in metres, and their rays in a field's frame.

Convention: the one of :func:`regnf.core.cameras.pinhole_rays`, OpenCV axes (x right,
y down, z forward), pixel ``(u, v)`` sampled at its centre ``(u + 0.5, v + 0.5)``, rays
row-major. ``camera_to_world`` is a RIGID pose in the world (metres) of the field: the
renderers map it into the field frame with ``inverse(field.to_world)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from regnf.captures.model import check_intrinsics, check_rigid_pose
from regnf.core.cameras import look_at, pinhole_rays
from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.fields.oriented_box import ArrayLike


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera in metres."""

    K: np.ndarray
    """(3, 3) float64 pinhole intrinsics, pixels (:func:`~regnf.captures.model.check_intrinsics`)."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    camera_to_world: np.ndarray
    """(4, 4) float64 rigid pose, camera -> world metres (:func:`~regnf.captures.model.check_rigid_pose`)."""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        C = np.asarray(self.camera_to_world, dtype=np.float64)
        # The capture loader's rules (one rule for training and rendering): a pose a capture
        # trains with renders, and one the renderer refuses never trained.
        try:
            check_intrinsics(K)
        except ValueError as exc:
            raise RegnfError(f"K: {exc}") from exc
        if int(self.width) != self.width or int(self.height) != self.height:
            raise RegnfError(f"width and height must be integers, got {self.width} x {self.height}")
        if self.width < 1 or self.height < 1:
            raise RegnfError(f"width and height must be >= 1, got {self.width} x {self.height}")
        try:
            check_rigid_pose(C)
        except ValueError as exc:
            raise RegnfError(f"camera_to_world: {exc}") from exc
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "camera_to_world", C)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 optical centre in world metres."""
        return self.camera_to_world[:3, 3].copy()

    @staticmethod
    def from_fov(width: int, height: int, fov_deg: float, camera_to_world: ArrayLike) -> Camera:
        """Square pixels, principal point at the image centre, HORIZONTAL field of view."""
        if not 0.0 < fov_deg < 180.0:
            raise RegnfError(f"fov_deg must be in (0, 180), got {fov_deg}")
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        return Camera(K, width, height, np.asarray(camera_to_world, dtype=np.float64))


def orbit_cameras(
    center: ArrayLike,
    radius: float,
    height: float,
    n: int,
    width: int,
    height_px: int,
    fov_deg: float,
) -> list[Camera]:
    """``n`` cameras evenly spaced on a horizontal circle, all looking at ``center``.

    Camera ``k`` sits at ``center + (radius cos a_k, radius sin a_k, height)`` with
    ``a_k = 2 pi k / n`` (world metres, +Z up): ``height`` is the offset ABOVE the centre.
    """
    if n < 1 or not radius > 0:
        raise RegnfError(f"need n >= 1 and radius > 0, got n={n}, radius={radius}")
    c = np.asarray(center, dtype=np.float64).reshape(3)
    cams = []
    for k in range(n):  # a handful of cameras, not a per-pixel loop
        a = 2.0 * math.pi * k / n
        eye = c + np.array([radius * math.cos(a), radius * math.sin(a), height])
        cams.append(Camera.from_fov(width, height_px, fov_deg, look_at(eye, c)))
    return cams


class CameraRays(NamedTuple):
    """A camera's pixel rays in a field's frame (on the field's device)."""

    origins: torch.Tensor
    """(h w, 3) float, field frame, row-major pixels."""
    dirs: torch.Tensor
    """(h w, 3) float unit directions, field frame."""
    z_scale: torch.Tensor
    """(h w,) float: cosine to the optical axis; z-depth = ``t * z_scale``."""
    pixel_angle: float
    """Angle subtended by one pixel at the image centre (radians): footprint = t * angle."""
    origin: torch.Tensor
    """(3,) float optical centre in the field frame."""


def camera_rays(field: Field, camera: Camera) -> CameraRays:
    """The rays of every pixel of ``camera`` in ``field``'s frame, in its working dtype."""
    world_to_field = np.linalg.inv(field.to_world.detach().cpu().double().numpy())
    cam_to_field = world_to_field @ camera.camera_to_world
    dtype = field.bounds.dtype
    o, d, z = pinhole_rays(
        camera.K, cam_to_field, camera.width, camera.height, device=field.device, dtype=dtype
    )
    angle = 1.0 / float(min(camera.K[0, 0], camera.K[1, 1]))
    origin = torch.as_tensor(cam_to_field[:3, 3], dtype=dtype, device=field.device)
    return CameraRays(o, d, z, angle, origin)
