"""Surface normals of a depth image: from central differences, or over windows for noisy depth.

An exact depth image (regnf's ideal renders) gives a normal per pixel from the central
differences of its back-projected neighbours (:func:`depth_normals`). A sensor's depth does not:
with an axial noise sigma of the order of a pixel footprint (6 mm at 2 m against an 11 mm
footprint at 180 px focal length) the difference of two neighbours is mostly noise, and the
normal is tens of degrees off. :func:`window_normals` sums the central-difference tangents over
a square window, the smallest that brings the normal's predicted error under a target
(:func:`normal_error`), and trusts no normal whose best window is still worse than a limit.
"""

from __future__ import annotations

import math

import numpy as np

EDGE_STEP_FOOTPRINTS = 8.0
"""A depth step between neighbouring pixels larger than this many pixel footprints (z / f) is
a discontinuity (an occluding edge), not a slanted surface."""

NORMAL_TARGET_DEG = 3.0
"""Predicted normal error a window is grown to reach, degrees (docs/decisions/depth-weights.md)."""
NORMAL_LIMIT_DEG = 10.0
"""Largest predicted normal error of a trusted normal, degrees (docs/decisions/depth-weights.md)."""
MAX_WINDOW_RADIUS = 4
"""Largest window radius of :func:`window_normals`, pixels (a 9 x 9 window)."""


def depth_normals(
    points: np.ndarray, depth: np.ndarray, valid: np.ndarray, K: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (h, w, 3) from central differences of back-projected points, and a mask.

    A pixel's normal is trusted only when its 4 neighbours have depth and no one-sided depth
    step exceeds :data:`EDGE_STEP_FOOTPRINTS` pixel footprints (a discontinuity, not a slanted
    surface).
    """
    du, dv, ok = _tangents(points, depth, valid, K)
    return _unit_facing(np.cross(du, dv), ok, dirs)


def normal_error(sigma: np.ndarray, footprint: np.ndarray, radius: int) -> np.ndarray:
    """Predicted standard deviation of a window normal's angle, radians.

    The central differences of a row of the window telescope to the difference of its two
    end pairs of points: an error of about 2 sigma over a baseline of 2 (2 r + 1) footprints,
    averaged over the window's 2 r + 1 rows; radius 0 is one difference of two points.

    Parameters
    ----------
    sigma : (...) float
        Axial depth noise, the units of ``footprint``.
    footprint : (...) float
        Pixel footprint z / f.
    radius : int
        Window radius r, pixels.
    """
    factor = math.sqrt(0.5) if radius == 0 else (2 * radius + 1) ** -1.5
    return np.arctan(factor * np.asarray(sigma) / np.maximum(np.asarray(footprint), 1e-300))


def window_normals(
    points: np.ndarray,
    depth: np.ndarray,
    valid: np.ndarray,
    K: np.ndarray,
    dirs: np.ndarray,
    sigma: np.ndarray,
    target_deg: float = NORMAL_TARGET_DEG,
    limit_deg: float = NORMAL_LIMIT_DEG,
    max_radius: int = MAX_WINDOW_RADIUS,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals of noisy depth from the central-difference tangents summed over square windows.

    Each pixel takes the smallest window (radius 0 to ``max_radius``) that lies wholly on
    trusted central-difference tangents (:func:`depth_normals`' rule: no pixel beside a hole or a
    discontinuity) and whose :func:`normal_error` is at most ``target_deg``; failing that the
    largest such window, if its error is at most ``limit_deg``; failing that no trusted normal.

    Parameters
    ----------
    points : (h, w, 3) float
        Back-projected points.
    depth : (h, w) float
        z-depth, the units of ``points``.
    valid : (h, w) bool
        Pixels whose depth is used.
    K : (3, 3) float
    dirs : (h, w, 3) float
        Unit ray directions (the normals face the camera).
    sigma : (h, w) float
        Axial depth noise at normal incidence, the units of ``depth``.
    target_deg, limit_deg : float
        Predicted normal errors, degrees.
    max_radius : int

    Returns
    -------
    normals : (h, w, 3) float64
        Unit normals facing the camera, 0 where not trusted.
    ok : (h, w) bool
    """
    du, dv, good = _tangents(points, depth, valid, K)
    footprint = depth / K[0, 0]
    target, limit = math.radians(target_deg), math.radians(limit_deg)
    parts = np.concatenate([du * good[..., None], dv * good[..., None], good[..., None]], -1)
    sums = _integral(parts)
    cross = np.zeros_like(points)
    chosen = np.zeros(depth.shape, dtype=bool)
    for radius in range(max_radius, -1, -1):  # a few window sizes, each over the whole image
        # Radius 0 from the tangents themselves: exactly depth_normals' normals.
        box = parts if radius == 0 else _box_sum(sums, radius)
        whole = box[..., 6] > (2 * radius + 1) ** 2 - 0.5
        error = normal_error(sigma, footprint, radius)
        take = whole & ((error <= target) | (~chosen & (error <= limit)))
        cross = np.where(take[..., None], np.cross(box[..., 0:3], box[..., 3:6]), cross)
        chosen |= take
    return _unit_facing(cross, chosen, dirs)


def _tangents(
    points: np.ndarray, depth: np.ndarray, valid: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Central-difference tangents du, dv (h, w, 3) (0 on the border) and where they are trusted."""
    h, w = depth.shape
    du = np.zeros_like(points)
    dv = np.zeros_like(points)
    ok = np.zeros((h, w), dtype=bool)
    c = (slice(1, -1), slice(1, -1))
    du[c] = points[1:-1, 2:] - points[1:-1, :-2]
    dv[c] = points[2:, 1:-1] - points[:-2, 1:-1]
    z = depth
    footprint = z[c] / K[0, 0]
    steps = np.stack(
        [
            np.abs(z[1:-1, 2:] - z[c]), np.abs(z[c] - z[1:-1, :-2]),
            np.abs(z[2:, 1:-1] - z[c]), np.abs(z[c] - z[:-2, 1:-1]),
        ],
        -1,
    ).max(-1)
    neigh = valid[c] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    ok[c] = neigh & (steps < EDGE_STEP_FOOTPRINTS * footprint)
    return du, dv, ok


def _unit_facing(n: np.ndarray, ok: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals facing the camera (against the viewing ray) where ``ok`` and non-zero, else 0."""
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = n / np.maximum(norm, 1e-12)
    n = np.where((n * dirs).sum(-1, keepdims=True) > 0, -n, n)
    ok = ok & (norm[..., 0] > 0)
    return np.where(ok[..., None], n, 0.0), ok


def _integral(x: np.ndarray) -> np.ndarray:
    """(h + 1, w + 1, c) summed-area table of ``x`` (h, w, c), with a zero first row and column."""
    table = np.zeros((x.shape[0] + 1, x.shape[1] + 1, x.shape[2]))
    table[1:, 1:] = x.cumsum(0).cumsum(1)
    return table


def _box_sum(table: np.ndarray, radius: int) -> np.ndarray:
    """(h, w, c) sums of the (2 r + 1)^2 windows around each pixel, clipped at the image border."""
    h, w = table.shape[0] - 1, table.shape[1] - 1
    y0 = np.clip(np.arange(h) - radius, 0, h)
    y1 = np.clip(np.arange(h) + radius + 1, 0, h)
    x0 = np.clip(np.arange(w) - radius, 0, w)
    x1 = np.clip(np.arange(w) + radius + 1, 0, w)
    return (table[y1][:, x1] - table[y0][:, x1] - table[y1][:, x0] + table[y0][:, x0])
