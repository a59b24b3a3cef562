"""The 8 procedural library objects of the ONR-like data set (5 chairs, 3 tables).

Canonical frame: metres, +Z up, +X forward (a seated person faces +X, so chair backs are at
-X), the base centred on the origin at z = 0. Each object is ONE watertight mesh (manifold
boolean union of its parts), so that a signed distance by ray parity is well defined, with
per-face albedo colours.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import trimesh

from regnf.captures.instance import Instance
from regnf.synthetic.primitives import (
    Part,
    box,
    canonicalise,
    cylinder,
    ellipsoid,
    horizontal_cylinder,
    union_parts,
)

LIBRARY_NAMES: tuple[str, ...] = ("c", "dc", "fc", "fc-nop", "mc", "et", "t", "wt")
"""Names of the library objects, chairs first."""

RGB = tuple[float, float, float]

# Albedos: natural woods and fabrics, distinct between objects so that colour helps matching.
WALNUT: RGB = (0.36, 0.22, 0.12)
OAK: RGB = (0.66, 0.48, 0.30)
CHERRY: RGB = (0.50, 0.20, 0.13)
PINE: RGB = (0.80, 0.64, 0.42)
DARK_WOOD: RGB = (0.22, 0.14, 0.08)
TEAK: RGB = (0.58, 0.36, 0.18)
SAGE: RGB = (0.42, 0.58, 0.33)
TEAL: RGB = (0.15, 0.45, 0.50)
CREAM: RGB = (0.86, 0.80, 0.64)
MUSTARD: RGB = (0.86, 0.62, 0.14)
COGNAC: RGB = (0.62, 0.33, 0.14)
OXBLOOD: RGB = (0.52, 0.11, 0.10)


@dataclass(frozen=True)
class LibraryObject:
    """A library object in its canonical frame."""

    name: str
    """Library name, one of :data:`LIBRARY_NAMES`."""
    label: str
    """Semantic class: ``chair`` or ``table``."""
    symmetry_order: int
    """Rotational symmetry about +Z: 1 none, k k-fold, 0 continuous."""
    mesh: trimesh.Trimesh
    """Watertight mesh in canonical metres with per-face RGBA colours."""


def _four(x: float, y: float) -> list[tuple[float, float]]:
    """The four (±x, ±y) corner positions."""
    return [(sx * x, sy * y) for sx in (1, -1) for sy in (1, -1)]


def _plain_chair() -> list[Part]:
    parts = [box((0.04, 0.04, 0.44), (x, y, 0.22), WALNUT, "leg") for x, y in _four(0.19, 0.19)]
    parts.append(box((0.44, 0.44, 0.04), (0.0, 0.0, 0.45), OAK, "seat"))
    parts.append(box((0.04, 0.44, 0.42), (-0.20, 0.0, 0.67), OAK, "back"))
    return parts


def _dining_chair() -> list[Part]:
    parts = [box((0.04, 0.04, 0.47), (0.20, y, 0.235), CHERRY, "front leg") for y in (0.2, -0.2)]
    # Rear legs continue up as the back posts.
    parts += [box((0.04, 0.04, 1.00), (-0.20, y, 0.50), CHERRY, "rear post") for y in (0.2, -0.2)]
    parts.append(box((0.48, 0.46, 0.05), (0.0, 0.0, 0.465), CHERRY, "seat"))
    parts.append(box((0.40, 0.38, 0.04), (0.02, 0.0, 0.505), SAGE, "cushion"))
    parts.append(box((0.04, 0.40, 0.08), (-0.20, 0.0, 0.94), CHERRY, "top rail"))
    # Vertical slats with 4 cm gaps between them.
    parts += [
        box((0.03, 0.04, 0.44), (-0.20, y, 0.70), CHERRY, "slat")
        for y in (-0.12, -0.04, 0.04, 0.12)
    ]
    return parts


def _armchair(pillow: bool) -> list[Part]:
    parts = [cylinder(0.03, 0.0, 0.11, xy, WALNUT, "leg") for xy in _four(0.33, 0.35)]
    parts.append(box((0.80, 0.82, 0.24), (0.0, 0.0, 0.22), TEAL, "base"))
    parts += [box((0.80, 0.14, 0.28), (0.0, y, 0.48), TEAL, "arm") for y in (0.34, -0.34)]
    parts.append(box((0.16, 0.82, 0.56), (-0.32, 0.0, 0.62), TEAL, "back"))
    parts.append(box((0.56, 0.54, 0.12), (0.04, 0.0, 0.40), CREAM, "seat cushion"))
    parts.append(box((0.12, 0.54, 0.40), (-0.18, 0.0, 0.66), CREAM, "back cushion"))
    if pillow:
        # Leans back onto the back cushion and sits on the seat cushion (overlaps both).
        parts.append(ellipsoid((0.07, 0.20, 0.16), (-0.07, 0.0, 0.62), MUSTARD, -0.25, "pillow"))
    return parts


def _club_chair() -> list[Part]:
    parts = [box((0.90, 0.92, 0.06), (0.0, 0.0, 0.03), DARK_WOOD, "plinth")]
    parts.append(box((0.95, 1.00, 0.34), (0.0, 0.0, 0.22), COGNAC, "body"))
    for y in (0.39, -0.39):
        parts.append(box((0.85, 0.22, 0.26), (0.05, y, 0.51), COGNAC, "arm"))
        parts.append(horizontal_cylinder(0.11, 0.85, (0.05, y, 0.64), COGNAC, "x", "arm roll"))
    parts.append(box((0.25, 1.00, 0.45), (-0.35, 0.0, 0.605), COGNAC, "back"))
    parts.append(horizontal_cylinder(0.125, 1.00, (-0.35, 0.0, 0.83), COGNAC, "y", "back roll"))
    parts.append(box((0.62, 0.56, 0.16), (0.085, 0.0, 0.46), OXBLOOD, "seat cushion"))
    return parts


def _end_table() -> list[Part]:
    parts = [
        box((0.045, 0.045, 0.52), (x, y, 0.26), DARK_WOOD, "leg") for x, y in _four(0.205, 0.205)
    ]
    parts.append(box((0.50, 0.50, 0.04), (0.0, 0.0, 0.53), PINE, "top"))
    parts.append(box((0.42, 0.42, 0.03), (0.0, 0.0, 0.155), PINE, "shelf"))
    return parts


def _rect_table() -> list[Part]:
    parts = [box((0.06, 0.06, 0.72), (x, y, 0.36), WALNUT, "leg") for x, y in _four(0.62, 0.32)]
    parts.append(box((1.40, 0.80, 0.04), (0.0, 0.0, 0.73), OAK, "top"))
    parts += [box((1.18, 0.03, 0.08), (0.0, y, 0.675), WALNUT, "apron") for y in (0.32, -0.32)]
    parts += [box((0.03, 0.58, 0.08), (x, 0.0, 0.675), WALNUT, "apron") for x in (0.62, -0.62)]
    return parts


def _round_table() -> list[Part]:
    return [
        cylinder(0.28, 0.0, 0.05, (0.0, 0.0), DARK_WOOD, "base"),
        cylinder(0.06, 0.04, 0.71, (0.0, 0.0), DARK_WOOD, "column"),
        cylinder(0.45, 0.70, 0.74, (0.0, 0.0), TEAK, "top"),
    ]


_SPECS: dict[str, tuple[str, int, Callable[[], list[Part]]]] = {
    "c": ("chair", 1, _plain_chair),
    "dc": ("chair", 1, _dining_chair),
    "fc": ("chair", 1, lambda: _armchair(pillow=True)),
    "fc-nop": ("chair", 1, lambda: _armchair(pillow=False)),
    "mc": ("chair", 1, _club_chair),
    "et": ("table", 4, _end_table),
    "t": ("table", 2, _rect_table),
    "wt": ("table", 0, _round_table),
}


@functools.cache
def _build(name: str) -> LibraryObject:
    label, order, make_parts = _SPECS[name]
    mesh = canonicalise(union_parts(make_parts(), context=f"library object {name!r}"))
    return LibraryObject(name, label, order, mesh)


def make_library_object(name: str) -> LibraryObject:
    """Build library object ``name`` (deterministic; a fresh mesh copy on each call).

    Raises
    ------
    KeyError
        If ``name`` is not one of :data:`LIBRARY_NAMES`.
    """
    if name not in _SPECS:
        raise KeyError(f"unknown library object {name!r}; expected one of {LIBRARY_NAMES}")
    obj = _build(name)
    return LibraryObject(obj.name, obj.label, obj.symmetry_order, obj.mesh.copy())


def library_label(name: str) -> str:
    """The class label (``chair`` / ``table``) of library object ``name``."""
    if name not in _SPECS:
        raise KeyError(f"unknown library object {name!r}; expected one of {LIBRARY_NAMES}")
    return _SPECS[name][0]


def library_object_names(label: str | None = None) -> tuple[str, ...]:
    """Library names, all of them or only those of class ``label``."""
    return tuple(n for n in LIBRARY_NAMES if label is None or _SPECS[n][0] == label)


def instance_mesh(inst: Instance) -> trimesh.Trimesh:
    """A placed instance's mesh in room metres (with its face colours).

    Read from ``inst.mesh_path`` when set, else built from the procedural library.

    Raises
    ------
    FileNotFoundError
        No mesh file and ``inst.library`` is not a library object.
    """
    if inst.mesh_path is not None and Path(inst.mesh_path).is_file():
        return trimesh.load(inst.mesh_path, force="mesh", process=False)
    if inst.library not in LIBRARY_NAMES:
        raise FileNotFoundError(
            f"instance {inst.id!r}: no mesh file ({inst.mesh_path}) and {inst.library!r} "
            "is not a procedural library object"
        )
    mesh = make_library_object(inst.library).mesh
    mesh.apply_transform(inst.object_to_world)
    return mesh
