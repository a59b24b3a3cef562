"""Coloured primitive parts and their boolean union into one watertight, face-coloured mesh.

Library objects and clutter are built from boxes, cylinders and ellipsoids. The parts overlap
a little where they join (a leg pokes into the seat) so that the manifold union is a single
closed solid; each face of the union is then coloured by the part it came from.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from regnf.core.errors import RegnfError

CYLINDER_SECTIONS = 64
"""Polygon sides of every cylinder; a multiple of 4 so that 4-fold symmetric layouts stay exact."""


@dataclass(frozen=True)
class Part:
    """One primitive solid of an object and its albedo."""

    mesh: trimesh.Trimesh
    """Closed primitive mesh, in the object's frame (metres)."""
    color: tuple[float, float, float]
    """Albedo, RGB in [0, 1]."""
    name: str = ""
    """Human-readable part name (seat, leg, ...), for debugging."""


def box(
    size: Sequence[float],
    center: Sequence[float],
    color: tuple[float, float, float],
    name: str = "",
) -> Part:
    """An axis-aligned box part.

    Parameters
    ----------
    size : (3,) float
        Extents along x, y, z in metres.
    center : (3,) float
        Box centre in metres.
    """
    mesh = trimesh.creation.box(extents=np.asarray(size, dtype=np.float64))
    mesh.apply_translation(np.asarray(center, dtype=np.float64))
    return Part(mesh, color, name)


def cylinder(
    radius: float,
    z0: float,
    z1: float,
    xy: Sequence[float],
    color: tuple[float, float, float],
    name: str = "",
) -> Part:
    """A vertical cylinder part standing from ``z0`` to ``z1`` with its axis through ``xy``."""
    mesh = trimesh.creation.cylinder(radius=radius, height=z1 - z0, sections=CYLINDER_SECTIONS)
    mesh.apply_translation([xy[0], xy[1], 0.5 * (z0 + z1)])
    return Part(mesh, color, name)


def horizontal_cylinder(
    radius: float,
    length: float,
    center: Sequence[float],
    color: tuple[float, float, float],
    axis: str = "x",
    name: str = "",
) -> Part:
    """A cylinder lying along the x or y axis (rolled arm rests), centred at ``center``."""
    if axis not in ("x", "y"):
        raise RegnfError(f"horizontal_cylinder: axis must be 'x' or 'y', got {axis!r}")
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=CYLINDER_SECTIONS)
    # A quarter turn about y lays the z-aligned cylinder along x; about x, along y.
    turn_axis = [0, 1, 0] if axis == "x" else [1, 0, 0]
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, turn_axis))
    mesh.apply_translation(np.asarray(center, dtype=np.float64))
    return Part(mesh, color, name)


def ellipsoid(
    radii: Sequence[float],
    center: Sequence[float],
    color: tuple[float, float, float],
    tilt_y: float = 0.0,
    name: str = "",
) -> Part:
    """An ellipsoid part (cushions, pillows), optionally tilted about y by ``tilt_y`` radians."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.apply_scale(np.asarray(radii, dtype=np.float64))
    if tilt_y:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(tilt_y, [0, 1, 0]))
    mesh.apply_translation(np.asarray(center, dtype=np.float64))
    return Part(mesh, color, name)


def union_parts(parts: Sequence[Part], context: str = "object") -> trimesh.Trimesh:
    """Boolean-union the parts into ONE watertight mesh and colour each face by its part.

    Parameters
    ----------
    parts : sequence of Part
        Closed primitives; touching or overlapping ones merge.
    context : str
        Name used in error messages.

    Returns
    -------
    trimesh.Trimesh
        Watertight union with per-face RGBA colours (``visual.kind == "face"``); vertices stay
        merged so that watertightness holds (renderers unmerge per face).
    """
    if not parts:
        raise RegnfError(f"{context}: no parts to union")
    union = trimesh.boolean.union([p.mesh for p in parts], engine="manifold")
    if not union.is_watertight:
        raise RuntimeError(f"{context}: boolean union is not watertight")
    union.visual.face_colors = color_faces_by_part(union, parts)
    return union


def surface_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """(n,) float32 unsigned distances from ``points`` (n, 3) to the triangles of ``mesh``."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()


def color_faces_by_part(mesh: trimesh.Trimesh, parts: Sequence[Part]) -> np.ndarray:
    """Per-face RGBA colours: each face takes the colour of the part nearest its centroid.

    Every face of a union lies on the surface of one of the parts, so its centroid is at
    (numerically) zero distance from that part.

    Returns
    -------
    (F, 4) uint8
    """
    dist = np.empty((len(parts), len(mesh.faces)), dtype=np.float32)
    for k, part in enumerate(parts):  # loop over parts (few), vectorised over faces
        dist[k] = surface_distance(part.mesh, mesh.triangles_center)
    palette = np.array([p.color for p in parts], dtype=np.float64)
    rgb = np.round(palette[np.argmin(dist, axis=0)] * 255.0).astype(np.uint8)
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, dtype=np.uint8)], axis=1)


def canonicalise(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Translate ``mesh`` in place so that min z = 0 and the xy bounding-box centre is 0."""
    lo, hi = mesh.bounds
    mesh.apply_translation([-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), -lo[2]])
    return mesh
