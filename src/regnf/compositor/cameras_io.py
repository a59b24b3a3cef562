"""Cameras to render from: a capture's trajectory, or an orbit inside the scene's bounds.

A capture (:func:`regnf.captures.formats.read_capture`) stores OpenCV camera-to-world
poses in its normalised frame and the pinhole ``K`` of its images (pixel centres at
``u + 0.5``); :meth:`~regnf.captures.model.Capture.camtoworld_metres` brings the poses
to metres, the frame of a scene field trained from that capture. Both conventions are the
compositor's own (:mod:`regnf.render.camera`), so nothing is flipped here. Resizing scales the
rows of ``K`` by the size ratios: with pixel-centre sampling this keeps every ray through the
same point of the image plane. A frame's lens distortion
(:attr:`~regnf.captures.model.CaptureFrame.distortion`) is not rendered: a
:class:`~regnf.render.camera.Camera` is a pinhole, so a distorted capture's views render
undistorted (the pinhole image of the same ``K`` and pose).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from regnf.captures.formats import read_capture
from regnf.captures.model import Capture
from regnf.core.cameras import look_at
from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.render.camera import Camera


def resized(camera: Camera, width: int, height: int) -> Camera:
    """``camera`` at another resolution: ``K`` rows scaled by ``width / w`` and ``height / h``."""
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise RegnfError(f"width and height must be integers >= 1, got {width} x {height}")
    scale = np.diag([width / camera.width, height / camera.height, 1.0])
    return Camera(scale @ camera.K, int(width), int(height), camera.camera_to_world)


def target_size(width: int, height: int, new_width: int | None, new_height: int | None) -> tuple[int, int]:
    """The output size: as given, or one side given and the other kept in proportion."""
    if new_width is None and new_height is None:
        return width, height
    if new_width is None:
        assert new_height is not None
        return max(1, round(width * new_height / height)), int(new_height)
    if new_height is None:
        return int(new_width), max(1, round(height * new_width / width))
    return int(new_width), int(new_height)


def cameras_from_capture(
    path: str | os.PathLike,
    width: int | None = None,
    height: int | None = None,
    indices: Sequence[int] | None = None,
) -> list[Camera]:
    """The cameras of a capture's frames, posed in metres, optionally resized.

    Parameters
    ----------
    path : str or PathLike
        A capture folder of any format (or its metadata file).
    width, height : int, optional
        Output size; one alone keeps the aspect ratio; none keeps the capture's.
    indices : sequence of int, optional
        Frames to keep (all by default), in this order.

    Raises
    ------
    regnf.captures.model.CaptureError
        A missing or malformed capture (the message names the file and the frame): poses and
        intrinsics are checked by :func:`~regnf.captures.formats.read_capture` with the
        rules :class:`~regnf.render.camera.Camera` applies, so a capture that trains renders.
    ValueError
        An index out of range.
    """
    capture, _ = read_capture(path)
    return capture_cameras(capture, width, height, indices)


def capture_cameras(
    capture: Capture,
    width: int | None = None,
    height: int | None = None,
    indices: Sequence[int] | None = None,
) -> list[Camera]:
    """The cameras of a capture already read (:func:`cameras_from_capture`'s, without reading it).

    Raises
    ------
    ValueError
        An index out of range.
    """
    w, h = target_size(capture.width, capture.height, width, height)
    chosen = range(len(capture.frames)) if indices is None else list(indices)
    cams = []
    for i in chosen:  # a loop over frames, not pixels
        if not 0 <= i < len(capture.frames):
            raise RegnfError(f"{capture.root}: frame index {i} out of range (0..{len(capture.frames) - 1})")
        frame = capture.frames[i]
        cam = Camera(frame.intrinsics, capture.width, capture.height, capture.camtoworld_metres(i))
        cams.append(cam if (w, h) == (capture.width, capture.height) else resized(cam, w, h))
    return cams


def field_bounds_metres(field: Field) -> np.ndarray:
    """(2, 3) float64 axis-aligned bounds in metres of ``field``'s bounds box."""
    lo, hi = field.bounds.detach().cpu().double().numpy()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    M = field.to_world.detach().cpu().double().numpy()
    world = corners @ M[:3, :3].T + M[:3, 3]
    return np.stack([world.min(axis=0), world.max(axis=0)])


@dataclass(frozen=True)
class OrbitConfig:
    """An orbit of cameras around the centre of a box (metres, +Z up)."""

    n: int = 8
    """Number of cameras, evenly spaced in azimuth."""
    width: int = 320
    """Image width in pixels."""
    height: int = 240
    """Image height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view, degrees."""
    radius: float | None = None
    """Horizontal distance from the target, metres; None: ``radius_fraction`` of the box."""
    radius_fraction: float = 0.4
    """Default radius as a fraction of the box's smaller horizontal side (inside a room's walls)."""
    target_height_fraction: float = 0.2
    """Height of the target above the box's bottom, as a fraction of the box's height."""
    elevation_deg: float = 30.0
    """Angle of the cameras above the horizontal plane of the target, degrees."""
    azimuth_offset_deg: float = 0.0
    """Azimuth of camera 0, degrees (the others follow at equal steps)."""

    def __post_init__(self) -> None:
        if self.n < 1 or self.width < 1 or self.height < 1:
            raise RegnfError(f"need n, width, height >= 1, got {self.n}, {self.width}, {self.height}")
        if not 0.0 < self.fov_deg < 180.0:
            raise RegnfError(f"fov_deg must be in (0, 180), got {self.fov_deg}")
        if self.radius is not None and not (math.isfinite(self.radius) and self.radius > 0):
            raise RegnfError(f"radius must be finite and > 0, got {self.radius}")
        if not self.radius_fraction > 0 or not -90.0 < self.elevation_deg < 90.0:
            raise RegnfError("need radius_fraction > 0 and -90 < elevation_deg < 90")
        if not math.isfinite(self.azimuth_offset_deg):
            raise RegnfError(f"azimuth_offset_deg must be finite, got {self.azimuth_offset_deg}")


def orbit_around_bounds(bounds: np.ndarray, config: OrbitConfig = OrbitConfig()) -> list[Camera]:
    """Cameras on a horizontal circle around the centre of ``bounds`` (2, 3) metres, looking at it.

    The target is the box's horizontal centre at ``target_height_fraction`` of its height
    (furniture stands low in a room); camera ``k`` sits at azimuth ``offset + 2 pi k / n``.
    """
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or not (b[1] > b[0]).all():
        raise RegnfError(f"bounds must be (2, 3) finite with max > min, got {b.tolist()}")
    size = b[1] - b[0]
    target = np.array([*(0.5 * (b[0, :2] + b[1, :2])), b[0, 2] + config.target_height_fraction * size[2]])
    radius = config.radius if config.radius is not None else config.radius_fraction * float(size[:2].min())
    up = radius * math.tan(math.radians(config.elevation_deg))
    cams = []
    for k in range(config.n):  # a handful of cameras
        a = math.radians(config.azimuth_offset_deg) + 2.0 * math.pi * k / config.n
        eye = target + np.array([radius * math.cos(a), radius * math.sin(a), up])
        cams.append(Camera.from_fov(config.width, config.height, config.fov_deg, look_at(eye, target)))
    return cams
