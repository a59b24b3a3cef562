"""The normalised frame of a metric capture that states no scene box: from cameras and depth.

A capture in metres (nerfstudio, a phone scan) gives no bounds; they are the axis-aligned box
of its camera centres and of robust percentiles of its back-projected depth (a few flying
pixels do not blow the box up; a wall seen by a whole frame is far above the 1 % cut, so the
scene is never cropped), then :func:`regnf.captures.model.normalisation` with the rooms' margin.
"""

from __future__ import annotations

import numpy as np

SCENE_MARGIN = 1.02
"""Multiplier on half the largest extent of a scene's bounds (rooms, metric captures)."""

DEPTH_PERCENTILES = (1.0, 99.0)
"""Percentiles (per axis) of the back-projected depth points that bound a metric capture."""

POINTS_PER_FRAME = 4096
"""About how many depth pixels per frame are back-projected for the bounds."""


def depth_points(depth: np.ndarray, K: np.ndarray, camtoworld: np.ndarray) -> np.ndarray:
    """World points of a subsample of a frame's valid depth pixels.

    Parameters
    ----------
    depth : (H, W) float
        Z-depth in metres, 0 = no depth.
    K : (3, 3) float
        Pinhole intrinsics; pixel centres at ``(u + 0.5, v + 0.5)``.
    camtoworld : (4, 4) float
        OpenCV camera-to-world in metres.

    Returns
    -------
    (m, 3) float64
        Points in metres, one per kept pixel with depth > 0.
    """
    h, w = depth.shape
    step = max(1, int(np.sqrt(h * w / POINTS_PER_FRAME)))
    v, u = np.mgrid[0:h:step, 0:w:step]
    z = depth[v, u].astype(np.float64)
    keep = z > 0
    u, v, z = u[keep] + 0.5, v[keep] + 0.5, z[keep]
    # Inverse of the pinhole projection, skew included.
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    cam = np.stack([x * z, y * z, z], axis=1)
    return cam @ camtoworld[:3, :3].T + camtoworld[:3, 3]


def metric_bounds(centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(2, 3) box of the camera centres and of the depth points' :data:`DEPTH_PERCENTILES`.

    Parameters
    ----------
    centres : (n, 3) float
        Camera centres in metres.
    points : (m, 3) float
        Back-projected depth points in metres (may be empty).

    Returns
    -------
    (2, 3) float64
        Min and max corner in metres.
    """
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    if len(points):
        plo, phi = np.percentile(points, DEPTH_PERCENTILES, axis=0)
        lo, hi = np.minimum(lo, plo), np.maximum(hi, phi)
    return np.stack([lo, hi]).astype(np.float64)
