"""Lens distortion of a capture's cameras: the OpenCV and OpenCV-fisheye models.

A frame with a :class:`Distortion` sees along rays that a pinhole ``K`` alone does not give:
pixel -> ray goes through ``K^-1`` and then :func:`undistort`; point -> pixel goes through
:func:`distort` and then ``K``. Coordinates in between are normalised image coordinates
``(x / z, y / z)`` of the OpenCV camera frame (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class Distortion:
    """The distortion coefficients of one camera (nerfstudio's and OpenCV's names)."""

    model: Literal["OPENCV", "OPENCV_FISHEYE"]
    """OPENCV: radial k1, k2, k3 and tangential p1, p2; OPENCV_FISHEYE: equidistant k1..k4."""
    k1: float = 0.0
    """First radial coefficient."""
    k2: float = 0.0
    """Second radial coefficient."""
    k3: float = 0.0
    """Third radial coefficient."""
    k4: float = 0.0
    """Fourth radial coefficient (OPENCV_FISHEYE only)."""
    p1: float = 0.0
    """First tangential coefficient (OPENCV only)."""
    p2: float = 0.0
    """Second tangential coefficient (OPENCV only)."""
