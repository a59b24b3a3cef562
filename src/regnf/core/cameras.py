"""Camera poses, pinhole rays, the OpenCV / OpenGL axis flip and the ray-box slab test: one of
each.

Conventions: our cameras and captures use OpenCV axes (x right, y down, z forward); nerfstudio's
``transforms.json``, pyrender and USD cameras use OpenGL axes (x right, y up, z backward). The
two differ by a flip of y and z, ``c2w_gl = c2w_cv @ OPENCV_TO_OPENGL`` (the flip is its own
inverse). Poses are (4, 4) float64 camera -> world matrices acting on column vectors. Pixel ``(u, v)``
(column, row) has its centre at ``(u + 0.5, v + 0.5)`` for the intrinsics ``K`` (as in
nerfstudio and sdfstudio).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numpy.typing import ArrayLike

from regnf.core.errors import RegnfError

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
        raise RegnfError(f"eye and target coincide at {e.tolist()}")
    z = z / np.linalg.norm(z)
    x = np.cross(z, u)
    if np.linalg.norm(x) < 1e-9 * np.linalg.norm(u):
        if fallback_up is None:
            raise RegnfError(f"the view direction {z.tolist()} is parallel to up {u.tolist()}")
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


def check_pinhole(
    K: torch.Tensor | np.ndarray, camtoworld: torch.Tensor | np.ndarray, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    Kt = (
        torch.as_tensor(
            np.asarray(K) if not isinstance(K, torch.Tensor) else K, dtype=torch.float64
        )
        .detach()
        .cpu()
    )
    C = (
        torch.as_tensor(
            np.asarray(camtoworld) if not isinstance(camtoworld, torch.Tensor) else camtoworld,
            dtype=torch.float64,
        )
        .detach()
        .cpu()
    )
    if (
        Kt.shape != (3, 3)
        or not bool(torch.isfinite(Kt).all())
        or abs(float(torch.linalg.det(Kt))) < 1e-12
    ):
        raise RegnfError(f"K must be a finite invertible 3x3 matrix, got {Kt.tolist()}")
    if C.shape != (4, 4) or not bool(torch.isfinite(C).all()):
        raise RegnfError(f"camtoworld must be a finite 4x4 matrix, got shape {tuple(C.shape)}")
    if abs(float(torch.linalg.det(C[:3, :3]))) < 1e-12:
        raise RegnfError("camtoworld has a singular rotation part")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise RegnfError(f"width and height must be positive integers, got {width} x {height}")
    return Kt, C


def rays_through(
    Kt: torch.Tensor, C: torch.Tensor, u: torch.Tensor, v: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """float64 rays through image points ``(u, v)`` (n,) each, in continuous pixel coordinates."""
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # (n, 3)
    d_cam = pix @ torch.linalg.inv(Kt).T
    R = C[:3, :3]
    dirs = torch.nn.functional.normalize(d_cam @ R.T, dim=-1)
    forward = torch.nn.functional.normalize(R[:, 2], dim=0)
    z_scale = dirs @ forward
    origins = C[:3, 3].expand_as(dirs)
    return origins, dirs, z_scale


def pinhole_rays(
    K: torch.Tensor | np.ndarray,
    camtoworld: torch.Tensor | np.ndarray,
    width: int,
    height: int,
    stride: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays through the centres of (every ``stride``-th) pixel of a pinhole camera.

    Pixel ``(u, v)`` (column, row) is sampled at ``(u + 0.5, v + 0.5)``; rays are ordered
    row-major (``v`` outer, ``u`` inner), ``u = 0, stride, 2 stride, ...``.

    Parameters
    ----------
    K : (3, 3) float
        Intrinsics.
    camtoworld : (4, 4) float
        Camera -> field-frame pose, OpenCV axes (x right, y down, z forward).
    width, height : int
        Image size in pixels.
    stride : int
        Keep every ``stride``-th pixel along both axes.
    device : torch.device or str, optional
        CPU by default.
    dtype : torch.dtype
        Of the outputs; rays are computed in float64 first.

    Returns
    -------
    origins : (n, 3) float
    dirs : (n, 3) float
        Unit directions.
    z_scale : (n,) float
        ``dot(dir, camera forward)``, so that z-depth = ``t * z_scale``.
    """
    Kt, C = check_pinhole(K, camtoworld, width, height)
    if int(stride) != stride or stride < 1:
        raise RegnfError(f"stride must be a positive integer, got {stride}")
    us = torch.arange(0, int(width), int(stride), dtype=torch.float64) + 0.5
    vs = torch.arange(0, int(height), int(stride), dtype=torch.float64) + 0.5
    v, u = torch.meshgrid(vs, us, indexing="ij")
    o, d, z = rays_through(Kt, C, u.reshape(-1), v.reshape(-1))
    return tuple(a.to(device=device, dtype=dtype) for a in (o, d, z))  # type: ignore[return-value]
