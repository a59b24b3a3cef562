"""A capture of a sphere seen from all around, written by test code in closed form (no renderer).

The sphere (radius ``RADIUS`` metres at ``CENTRE``) is seen by ``N_VIEWS`` cameras on a larger
sphere around it, some from below its lowest point, each looking at its centre with +Z as up
(:func:`regnf.core.cameras.look_at`); each pixel's exact z-depth is a ray-sphere intersection,
0 where the ray misses (the void around an object in an ideal render).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regnf.captures.model import Capture, normalisation
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.core.cameras import look_at
from regnf.synthetic.trajectories import fibonacci_directions

RADIUS = 0.3
"""Sphere radius, metres."""
CENTRE = np.array([0.5, -0.2, 1.0])
"""Sphere centre, metres."""
DISTANCE = 1.2
"""Camera distance from the centre, metres."""
N_VIEWS = 12
W, H = 32, 24
"""Image size, pixels."""
K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])


def poses() -> np.ndarray:
    """(N_VIEWS, 4, 4) OpenCV camera-to-world, metres, elevations -60 to 75 degrees."""
    eyes = CENTRE + DISTANCE * fibonacci_directions(N_VIEWS, -60.0, 75.0)
    return np.stack([look_at(e, CENTRE) for e in eyes])


def sphere_depth(pose: np.ndarray) -> np.ndarray:
    """(H, W) exact z-depth of the sphere from ``pose``, 0 where the ray misses."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1) @ pose[:3, :3].T
    oc = pose[:3, 3] - CENTRE
    a, b, c = (rays * rays).sum(-1), 2.0 * rays @ oc, oc @ oc - RADIUS**2
    disc = b * b - 4.0 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)  # rays have unit z: t is z-depth
    return np.where(disc > 0, t, 0.0)


def write_sphere_capture(root: Path, meta: dict | None = None) -> Capture:
    """Write the capture (sdfstudio, depth in metres, zero depth empty unless ``meta`` says) and load it."""
    P = poses()
    rng = np.random.default_rng(0)
    rgbs = [rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in P]
    bounds = np.stack([CENTRE - RADIUS, CENTRE + RADIUS])
    write_capture(root, rgbs, [sphere_depth(p) for p in P], P, K, normalisation(bounds, 1.15),
                  meta={"zero_depth": "empty"} if meta is None else meta)
    return load_capture(root)
