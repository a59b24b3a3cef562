"""Analytic scenes and closed-form truths (numpy, float64) for the compositor tests.

The truths here are written independently of the code under test: plain numpy formulas
for the SDFs of spheres, boxes and planes, and ray-sphere / ray-plane intersections.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from regnf.fields.analytic import Box, Sphere, Union
from regnf.fields.field import Field
from regnf.fields.similarity import similarity_matrix

# Scene (scene field frame = metres, identity to_world): a floor slab whose top is z = 0,
# and a sphere "object" hovering above it.
FLOOR_HALF = np.array([2.0, 2.0, 0.1])
FLOOR_CENTER = np.array([0.0, 0.0, -0.1])
OBJ_CENTER = np.array([0.5, 0.0, 0.4])
OBJ_RADIUS = 0.3
FLOOR_COLOR = (0.6, 0.5, 0.4)
OBJ_COLOR = (0.9, 0.1, 0.1)

# Removal box around the scene object, rotated about z, sparing the floor.
REGION_CENTER = np.array([0.5, 0.0, 0.4])
REGION_HALF = np.array([0.4, 0.4, 0.5])
REGION_ROT = Rotation.from_euler("z", 30, degrees=True).as_matrix()
FLOOR_Z = 0.0
FLOOR_MARGIN = 0.01

# Library sphere: radius 0.1 around an off-centre point of its own frame, placed with
# scale 2 (radius 0.2 in the scene), a rotation and a translation.
LIB_RADIUS = 0.1
LIB_CENTER = np.array([0.05, 0.0, 0.0])
LIB_COLOR = (0.1, 0.8, 0.3)
LIB_SCALE = 2.0
LIB_ROT = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
LIB_T = np.array([-0.6, 0.3, 0.5])
LIB_TO_SCENE = similarity_matrix(LIB_ROT, LIB_T, LIB_SCALE)
PLACED_CENTER = LIB_SCALE * LIB_ROT @ LIB_CENTER + LIB_T
PLACED_RADIUS = LIB_SCALE * LIB_RADIUS
INSTANCE = 7


def scene_field() -> Field:
    floor = Box(FLOOR_HALF, FLOOR_CENTER, color=FLOOR_COLOR, name="floor")
    obj = Sphere(OBJ_RADIUS, OBJ_CENTER, color=OBJ_COLOR, name="obj")
    return Union(floor, obj, label="scene", name="room")


def library_sphere() -> Sphere:
    return Sphere(LIB_RADIUS, LIB_CENTER, color=LIB_COLOR, label="ball", name="lib_ball")


# -- closed forms ----------------------------------------------------------------------
def sphere_sdf(x: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    return np.linalg.norm(x - c, axis=-1) - r


def box_sdf(x: np.ndarray, c: np.ndarray, h: np.ndarray, R: np.ndarray | None = None) -> np.ndarray:
    """Exact SDF of a box with axes R (columns), written out independently."""
    local = (x - c) @ (np.eye(3) if R is None else R)
    q = np.abs(local) - h
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def floor_sdf(x: np.ndarray) -> np.ndarray:
    return box_sdf(x, FLOOR_CENTER, FLOOR_HALF)


def region_sdf(x: np.ndarray) -> np.ndarray:
    """The removal region: rotated box intersected with z >= floor + margin."""
    return np.maximum(
        box_sdf(x, REGION_CENTER, REGION_HALF, REGION_ROT), FLOOR_Z + FLOOR_MARGIN - x[:, 2]
    )


def composite_truth(x: np.ndarray) -> np.ndarray:
    """max(min(floor, obj), -region) then min with the placed sphere (scene units)."""
    scene = np.minimum(floor_sdf(x), sphere_sdf(x, OBJ_CENTER, OBJ_RADIUS))
    masked = np.maximum(scene, -region_sdf(x))
    return np.minimum(masked, sphere_sdf(x, PLACED_CENTER, PLACED_RADIUS))


def expected_geometry_sdf(x: np.ndarray) -> np.ndarray:
    """Exact SDF of what the composite should show: the floor and the placed sphere."""
    return np.minimum(floor_sdf(x), sphere_sdf(x, PLACED_CENTER, PLACED_RADIUS))


def random_points(n: int, seed: int = 0, lo=(-1.2, -1.2, -0.3), hi=(1.2, 1.2, 1.2)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(lo, hi, size=(n, 3))


def tensor(x: np.ndarray, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.as_tensor(x, dtype=dtype)


# -- rays ------------------------------------------------------------------------------
def pixel_rays(K: np.ndarray, pose: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixel centres, row-major, OpenCV axes (independent of the code)."""
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=-1)
    d = (pix @ np.linalg.inv(K).T) @ pose[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(pose[:3, 3], d.shape).copy(), d


def ray_sphere(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float):
    """(hit, t, miss distance) of unit rays with a sphere: first hit in front of the origin.

    ``miss distance`` is the ray's closest approach to the centre minus the radius.
    """
    oc = o - c
    b = np.einsum("ij,ij->i", d, oc)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    closest = np.linalg.norm(oc - b[:, None] * d, axis=-1)
    return (disc > 0) & (t > 0), np.where((disc > 0) & (t > 0), t, np.inf), closest - r


def ray_plane_z(o: np.ndarray, d: np.ndarray, z: float) -> np.ndarray:
    """t of the first crossing of the plane at height ``z`` from above; inf if none."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z - o[:, 2]) / d[:, 2]
    return np.where((d[:, 2] < 0) & (t > 0), t, np.inf)
