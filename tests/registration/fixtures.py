"""Analytic test objects for the registration tests (shared, exact, fast).

``make_object()`` is an asymmetric chair-sized object in its canonical frame (+Z up, base on
z = 0, metres): an "L" of two boxes (base slab and back) plus a sphere and a post placed off
the mirror planes, so that no rotation or reflection maps it onto itself.
"""

from __future__ import annotations

import math

import numpy as np

from regnf.fields.analytic import Box, Cylinder, Sphere, Transformed, Union
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.fields.similarity import similarity_matrix

OBJECT_LO = np.array([-0.4, -0.25, 0.0])
"""Canonical AABB of :func:`make_object` (exact: the union of the parts' boxes)."""
OBJECT_HI = np.array([0.4, 0.25, 0.75])


def make_object() -> Field:
    """The asymmetric test object (canonical frame, field frame = canonical)."""
    base = Box(half_extents=(0.4, 0.25, 0.05), center=(0.0, 0.0, 0.05), color=(0.8, 0.2, 0.2))
    back = Box(half_extents=(0.05, 0.25, 0.35), center=(-0.35, 0.0, 0.4), color=(0.2, 0.8, 0.2))
    ball = Sphere(radius=0.12, center=(0.2, 0.1, 0.22), color=(0.2, 0.2, 0.8))
    post = Cylinder(radius=0.04, half_height=0.2, center=(0.25, -0.15, 0.3))
    return Union(base, back, ball, post, label="chair", name="testobj")


def object_box() -> OrientedBox:
    """The object's canonical AABB as a proposal."""
    return OrientedBox.from_aabb(OBJECT_LO, OBJECT_HI)


def rot(axis: np.ndarray | list[float], angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) about ``axis`` by ``angle`` radians (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def placement(axis: list[float], angle: float, t: list[float], s: float) -> np.ndarray:
    """(4, 4) similarity object -> scene."""
    return np.asarray(similarity_matrix(rot(axis, angle), np.asarray(t, dtype=float), s))


def make_scene(M: np.ndarray, floor: bool = True) -> Field:
    """The object placed by ``M`` (object -> scene), on a floor slab below z = 0 if ``floor``.

    With ``floor`` the placement must keep the base on z = 0 (yaw, translation in x, y, scale).
    """
    obj = Transformed(make_object(), M, name="placed")
    if not floor:
        return obj
    slab = Box(half_extents=(3.0, 3.0, 0.05), center=(0.0, 0.0, -0.05), color=(0.5, 0.5, 0.5))
    return Union(slab, obj, label="scene", name="room")
