"""Camera poses, the OpenCV / OpenGL axis flip and the ray-box slab test: one of each.

Conventions: our cameras and captures use OpenCV axes (x right, y down, z forward); nerfstudio's
``transforms.json``, pyrender and USD cameras use OpenGL axes (x right, y up, z backward). The
two differ by a flip of y and z, ``c2w_gl = c2w_cv @ OPENCV_TO_OPENGL`` (the flip is its own
inverse). Poses are (4, 4) float64 camera -> world matrices acting on column vectors.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numpy.typing import ArrayLike

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplied onto an OpenCV camera -> world pose, gives the OpenGL one (and back)."""


def opencv_to_opengl(camera_to_world: ArrayLike) -> np.ndarray:
    """(4, 4) float64 OpenGL camera -> world pose of an OpenCV one (and the reverse)."""
    return np.asarray(camera_to_world, dtype=np.float64) @ OPENCV_TO_OPENGL


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0),
            fallback_up: ArrayLike | None = None) -> np.ndarray:
    """(4, 4) float64 OpenCV camera -> world pose at ``eye`` looking at ``target``.

    Parameters
    ----------
    eye, target : (3,) float
        Camera centre and the point it looks at.
    up : (3,) float
        World up: the camera's y axis (image down) is as close to ``-up`` as the view
        direction allows.
    fallback_up : (3,) float, optional
        Used instead of ``up`` when the view direction is parallel to ``up`` (a camera looking
        straight down, as the captures' top views do). None: such a camera is an error.

    Raises
    ------
    ValueError
        ``eye == target``, or the view direction parallel to ``up`` without a fallback.
    """
    e, g, u = (np.asarray(v, dtype=np.float64).reshape(3) for v in (eye, target, up))
    z = g - e
    if np.linalg.norm(z) < 1e-12:
        raise ValueError(f"eye and target coincide at {e.tolist()}")
    z = z / np.linalg.norm(z)
    x = np.cross(z, u)
    if np.linalg.norm(x) < 1e-9 * np.linalg.norm(u):
        if fallback_up is None:
            raise ValueError(f"the view direction {z.tolist()} is parallel to up {u.tolist()}")
        x = np.cross(z, np.asarray(fallback_up, dtype=np.float64).reshape(3))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = e
    return pose


def ray_aabb(
    origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: entry and exit ``t`` (n,) each of rays into the box ``[lo, hi]`` (3,).

    Parameters
    ----------
    origins, dirs : (n, 3) float
        The rays (``dirs`` need not be unit vectors; ``t`` is in units of ``dirs``).
    lo, hi : (3,) float
        The box's corners.

    ``t_in > t_out`` means the line misses the box; ``t_in`` may be negative (the origin is
    inside or the box is behind). Axis-parallel rays are handled without NaNs.
    """
    inside = (origins >= lo) & (origins <= hi)  # (n, 3)
    inv = 1.0 / dirs  # +-inf on zero components, fixed below
    ta, tb = (lo - origins) * inv, (hi - origins) * inv
    tmin, tmax = torch.minimum(ta, tb), torch.maximum(ta, tb)
    # A zero direction component: the slab is everything (origin within it) or nothing.
    zero = dirs == 0
    inf = torch.full_like(tmin, math.inf)
    tmin = torch.where(zero, torch.where(inside, -inf, inf), tmin)
    tmax = torch.where(zero, torch.where(inside, inf, -inf), tmax)
    return tmin.max(dim=-1).values, tmax.min(dim=-1).values
