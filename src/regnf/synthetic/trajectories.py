"""Camera trajectories: cam-to-world 4x4 poses in the OpenCV convention.

OpenCV camera axes: x right, y down, z forward (the viewing direction). All poses here are in
metres in the captured geometry's frame (object canonical frame or room frame).
"""

from __future__ import annotations

import numpy as np

from regnf.core.cameras import look_at

X_AXIS = (1.0, 0.0, 0.0)
"""Image up of a camera that looks straight down (where world +Z cannot be)."""

MIN_EYE_HEIGHT = 1.2
"""Room cameras stay above this height: all furniture is lower, so no eye is inside an object."""


def viewing_distance(radius: float, K: np.ndarray, width: int, height: int, fill: float) -> float:
    """Distance at which a sphere of ``radius`` spans ``fill`` of the image's smaller half-FOV."""
    half_tan = min(0.5 * width / K[0, 0], 0.5 * height / K[1, 1])
    return float(radius / np.sin(np.arctan(fill * half_tan)))


def fibonacci_directions(n: int, elev_min_deg: float, elev_max_deg: float) -> np.ndarray:
    """Unit directions spread evenly (equal area) over a band of elevations.

    Returns
    -------
    (n, 3) float64
    """
    k = np.arange(n, dtype=np.float64)
    lo, hi = np.sin(np.radians([elev_min_deg, elev_max_deg]))
    z = lo + (hi - lo) * (k + 0.5) / n
    azimuth = k * np.pi * (3.0 - np.sqrt(5.0))  # golden angle
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def object_capture_poses(
    center: np.ndarray,
    radius: float,
    n: int,
    K: np.ndarray,
    width: int,
    height: int,
    fill: float = 0.9,
    elev_range_deg: tuple[float, float] = (-35.0, 80.0),
) -> np.ndarray:
    """Cameras on a sphere around an object, all looking at its centre.

    Parameters
    ----------
    center : (3,) float
        Look-at point (the object's bounding-box centre).
    radius : float
        Bounding-sphere radius of the object; sets the distance so that it fills the image.
    n : int
        Number of views.
    K : (3, 3) float
        Intrinsics.

    Returns
    -------
    (n, 4, 4) float64
    """
    dist = viewing_distance(radius, K, width, height, fill)
    eyes = np.asarray(center) + dist * fibonacci_directions(n, *elev_range_deg)
    return np.stack([look_at(e, center, fallback_up=X_AXIS) for e in eyes])


def _clamp_xy(eyes: np.ndarray, half_extent: tuple[float, float], margin: float) -> np.ndarray:
    """Clamp eye positions (n, 3) into the room interior, ``margin`` from the walls."""
    out = eyes.copy()
    out[:, 0] = np.clip(out[:, 0], -half_extent[0] + margin, half_extent[0] - margin)
    out[:, 1] = np.clip(out[:, 1], -half_extent[1] + margin, half_extent[1] - margin)
    return out


def room_full_coverage_poses(
    half_extent: tuple[float, float],
    object_centers: np.ndarray,
    object_radii: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    n: int = 120,
    seed: int = 0,
    heights: tuple[float, float] = (1.3, 1.9),
    max_elevation_deg: float = 55.0,
    overview_fraction: float = 1.0 / 6.0,
    wall_margin: float = 0.2,
) -> np.ndarray:
    """Per-object orbits at two heights plus overview views: every object seen from all sides.

    Parameters
    ----------
    half_extent : (2,) float
        Room interior half sizes along x and y (the room is centred on the origin).
    object_centers : (m, 3) float
        Bounding-box centres of the objects (look-at points).
    object_radii : (m,) float
        Bounding-sphere radii of the objects.
    n : int
        Total number of frames.

    Returns
    -------
    (n, 4, 4) float64
    """
    rng = np.random.default_rng(seed)
    m = len(object_centers)
    n_over = max(4, round(n * overview_fraction)) if m else n
    n_over = min(n_over, n)
    per_obj = np.full(m, (n - n_over) // max(m, 1))
    per_obj[: (n - n_over) - per_obj.sum()] += 1
    poses = []
    for c, r, k in zip(np.asarray(object_centers), np.asarray(object_radii), per_obj):
        dist = viewing_distance(float(r), K, width, height, fill=0.75)
        ring = np.arange(k) % len(heights)
        # Alternate rings; each ring's azimuths evenly spaced with a random start.
        phase = rng.uniform(0, 2 * np.pi, size=len(heights))
        idx_in_ring = np.arange(k) // len(heights)
        count_in_ring = np.bincount(ring, minlength=len(heights))
        az = phase[ring] + 2 * np.pi * idx_in_ring / np.maximum(count_in_ring[ring], 1)
        eye_z = np.maximum(np.asarray(heights)[ring], MIN_EYE_HEIGHT)
        # Keep the slant distance where possible, but never look down more steeply than
        # max_elevation_deg (small objects would otherwise be seen from straight above).
        dz = eye_z - c[2]
        horiz = np.maximum(
            np.sqrt(np.maximum(dist**2 - dz**2, 0.0)), dz / np.tan(np.radians(max_elevation_deg))
        )
        eyes = np.stack([c[0] + horiz * np.cos(az), c[1] + horiz * np.sin(az), eye_z], axis=1)
        eyes = _clamp_xy(eyes, half_extent, wall_margin)
        poses += [look_at(e, c, fallback_up=X_AXIS) for e in eyes]
    # Overviews from an ellipse near the walls, looking across the room at the middle.
    az = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_over) / max(n_over, 1)
    eyes = np.stack(
        [
            0.85 * half_extent[0] * np.cos(az),
            0.85 * half_extent[1] * np.sin(az),
            np.full(n_over, 2.2),
        ],
        axis=1,
    )
    targets = np.concatenate([rng.normal(0.0, 0.3, size=(n_over, 2)), np.full((n_over, 1), 0.4)], 1)
    poses += [look_at(e, t, fallback_up=X_AXIS) for e, t in zip(eyes, targets)]
    return np.stack(poses)


def room_low_coverage_poses(
    half_extent: tuple[float, float],
    object_centers: np.ndarray,
    n: int = 30,
    arc_deg: float = 70.0,
    eye_height: float = 1.5,
    wall_margin: float = 0.3,
) -> np.ndarray:
    """A short arc along the room's -y side, looking towards the objects.

    Only the sides of objects facing -y are seen; their backs (facing +y) never are.

    Returns
    -------
    (n, 4, 4) float64
    """
    centres = np.asarray(object_centers, dtype=np.float64).reshape(-1, 3)
    focus = centres.mean(axis=0) if len(centres) else np.array([0.0, 0.0, 0.4])
    t = np.linspace(-0.5, 0.5, n)
    az = -np.pi / 2 + np.radians(arc_deg) * t
    eyes = np.stack(
        [
            (half_extent[0] - wall_margin) * np.cos(az),
            (half_extent[1] - wall_margin) * np.sin(az),
            np.full(n, max(eye_height, MIN_EYE_HEIGHT)),
        ],
        axis=1,
    )
    # The look-at point pans with the camera so that the arc sweeps across the objects.
    spread = np.ptp(centres[:, 0]) if len(centres) else 1.0
    targets = focus + np.outer(t * 0.6 * spread, [1.0, 0.0, 0.0])
    return np.stack([look_at(e, g, fallback_up=X_AXIS) for e, g in zip(eyes, targets)])
