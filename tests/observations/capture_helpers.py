"""A small RGB-D capture of an ANALYTIC object, for tests of training and sample building.

The object is the union of an axis-aligned box (flat faces, sharp edges) and a sphere
sitting on it, both with constant colours. It fills the normalised frame like a library
object does (longest extent ~1.5 of the [-1, 1] box). Forty 64 x 64 views on a sphere
around it are sphere-traced with :func:`regnf.render.sphere_render.render` (OpenCV
cameras, z-depth in the normalised frame) and written with
:func:`regnf.captures.sdfstudio.write_capture` in METRES through a known similarity
``WORLDTOGT``, so loading the capture exercises the metres -> normalised conversion too.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch

from regnf.captures.model import Capture
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.core.cameras import look_at
from regnf.fields.analytic import Box, Sphere, Union
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.render.sphere_tracer import SphereTracerConfig
from regnf.synthetic.trajectories import fibonacci_directions, viewing_distance

BOX_HALF = np.array([0.75, 0.55, 0.35])
BOX_CENTER = np.array([0.0, 0.0, -0.25])
BOX_COLOR = (0.8, 0.25, 0.2)
SPHERE_RADIUS = 0.45
SPHERE_CENTER = np.array([0.15, 0.0, 0.3])
SPHERE_COLOR = (0.2, 0.35, 0.85)
BOUNDING_RADIUS = 1.12
"""Radius of a sphere about the origin containing the object (box corners: 1.109)."""

WIDTH = HEIGHT = 64
FOCAL = 70.0
K = np.array([[FOCAL, 0.0, WIDTH / 2], [0.0, FOCAL, HEIGHT / 2], [0.0, 0.0, 1.0]])
N_VIEWS = 40
TEST_EVERY = 8
"""Every 8th frame (0, 8, 16, ...) is held out with split ``test``."""
ELEVATIONS_DEG = (-60.0, 75.0)
"""Views from below too, so that the bottom face is observed."""

WORLD_SCALE = 0.4
WORLD_OFFSET = np.array([1.0, -2.0, 0.5])
WORLDTOGT = np.diag([WORLD_SCALE, WORLD_SCALE, WORLD_SCALE, 1.0])
WORLDTOGT[:3, 3] = WORLD_OFFSET
"""Normalised -> metres: metres = 0.4 * normalised + (1, -2, 0.5)."""


IDEAL_META = {"zero_depth": "empty"}
"""The ``regnf`` block of a test capture rendered exactly: its zero depths are rays that hit nothing."""


TRACE = SphereTracerConfig(max_steps=1024, background=(0.0, 0.0, 0.0))
"""Rays grazing a box face need many steps to converge; with the default 256 some pixels could
come out empty although their rays enter the box."""


def analytic_object() -> Union:
    """The captured object as an exact analytic field (normalised frame)."""
    box = Box(BOX_HALF, BOX_CENTER, color=BOX_COLOR)
    sphere = Sphere(SPHERE_RADIUS, SPHERE_CENTER, color=SPHERE_COLOR)
    return Union(box, sphere)


def camera_poses() -> np.ndarray:
    """(N_VIEWS, 4, 4) OpenCV cam-to-world poses in the normalised frame, facing the origin."""
    dist = viewing_distance(BOUNDING_RADIUS, K, WIDTH, HEIGHT, fill=0.95)
    eyes = dist * fibonacci_directions(N_VIEWS, *ELEVATIONS_DEG)
    return np.stack([look_at(e, np.zeros(3)) for e in eyes])


def splits() -> list[str]:
    return ["test" if i % TEST_EVERY == 0 else "train" for i in range(N_VIEWS)]


@functools.lru_cache(maxsize=1)
def rendered_views() -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...], np.ndarray]:
    """Colour (uint8), z-depth (normalised units, 0 = miss) and poses of every view (cached)."""
    field = analytic_object()
    poses = camera_poses()
    rgbs, depths = [], []
    for c2w in poses:
        out = render(field, Camera(K, WIDTH, HEIGHT, c2w), TRACE)  # to_world = I: metres = normalised
        rgbs.append(np.round(out.rgb.numpy() * 255.0).astype(np.uint8))
        depths.append(out.depth.numpy().astype(np.float64))
    return tuple(rgbs), tuple(depths), poses


def poses_in_metres(poses: np.ndarray) -> np.ndarray:
    out = poses.copy()
    out[:, :3, 3] = poses[:, :3, 3] * WORLD_SCALE + WORLD_OFFSET
    return out


def write_analytic_capture(
    out_dir: Path, with_depth: bool = True, frame_splits: list[str] | None = None
) -> Capture:
    """Write the capture to ``out_dir`` (depth in metres, as a sensor gives it) and load it."""
    rgbs, depths, poses = rendered_views()
    depth_m = [d * WORLD_SCALE for d in depths] if with_depth else None
    write_capture(
        out_dir,
        list(rgbs),
        depth_m,
        poses_in_metres(poses),
        K,
        WORLDTOGT,
        splits=splits() if frame_splits is None else frame_splits,
        meta=IDEAL_META,
    )
    return load_capture(out_dir)


def surface_samples(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """About ``n`` points (m, 3) on the union's surface and (m,) bool "on the sphere".

    Drawn area-uniformly on the box faces and on the sphere, keeping the points that lie on
    the boundary of the union (not inside the other solid), checked in closed form.
    """
    rng = np.random.default_rng(seed)
    b = BOX_HALF
    areas = np.array([b[1] * b[2], b[1] * b[2], b[0] * b[2], b[0] * b[2], b[0] * b[1], b[0] * b[1]])
    sphere_area = np.pi * SPHERE_RADIUS**2  # 4 pi r^2 / 4: area ratio only sets the mix
    n_box = int(n * areas.sum() * 4 / (areas.sum() * 4 + 4 * sphere_area))
    face = rng.choice(6, size=n_box, p=areas / areas.sum())
    p = rng.uniform(-1.0, 1.0, size=(n_box, 3)) * b
    axis, sign = face // 2, np.where(face % 2 == 0, -1.0, 1.0)
    p[np.arange(n_box), axis] = sign * b[axis]
    box_pts = p + BOX_CENTER
    v = rng.normal(size=(n - n_box, 3))
    sph_pts = SPHERE_CENTER + SPHERE_RADIUS * v / np.linalg.norm(v, axis=1, keepdims=True)
    in_sphere = np.linalg.norm(box_pts - SPHERE_CENTER, axis=1) < SPHERE_RADIUS
    in_box = np.all(np.abs(sph_pts - BOX_CENTER) < BOX_HALF, axis=1)
    pts = np.concatenate([box_pts[~in_sphere], sph_pts[~in_box]])
    on_sphere = np.concatenate([np.zeros((~in_sphere).sum(), bool), np.ones((~in_box).sum(), bool)])
    return pts, on_sphere


def analytic_sdf(points: np.ndarray) -> np.ndarray:
    """Exact SDF (n,) of the union at points (n, 3), float64 (independent of the field code)."""
    q = np.abs(points - BOX_CENTER) - BOX_HALF
    box = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
    sphere = np.linalg.norm(points - SPHERE_CENTER, axis=1) - SPHERE_RADIUS
    return np.minimum(box, sphere)


def as_tensor(points: np.ndarray, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(points)).to(dtype)


def pixel_dirs_camera(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(h, w, 3) rays K^-1 [u + 0.5, v + 0.5, 1] (z component 1) in the camera frame."""
    v, u = np.mgrid[0:h, 0:w] + 0.5
    pix = np.stack([u, v, np.ones_like(u)], -1)
    return pix @ np.linalg.inv(K).T


def box_face_id(points: np.ndarray, tol: float = 1e-4) -> np.ndarray:
    """(...) int: 0..5 for the box face (axis * 2 + (side > 0)) a point lies on, -1 otherwise.

    A point counts only if it is on the union's surface there (outside the sphere).
    """
    q = points - BOX_CENTER
    out = np.full(points.shape[:-1], -1)
    on_box = np.all(np.abs(q) <= BOX_HALF + tol, axis=-1)
    outside_sphere = np.linalg.norm(points - SPHERE_CENTER, axis=-1) > SPHERE_RADIUS + tol
    for axis in range(3):
        for side in (0, 1):
            sign = 1.0 if side else -1.0
            on = on_box & outside_sphere & (np.abs(q[..., axis] - sign * BOX_HALF[axis]) < tol)
            out[on] = 2 * axis + side
    return out
