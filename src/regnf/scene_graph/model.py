"""A composed scene in plain Python: the scene field, the library and the registered instances.

This is what a stage records and what :func:`regnf.scene_graph.read_stage` gives back; USD is only
its storage. Matrices act on column vectors (``y = M x``) and are float64.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from regnf.meshes.source_mesh import SourceMesh

FORMAT_VERSION = 1
"""Version of the stage layout below; written into the stage's ``customLayerData``."""

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
"""Library and scene names: they become file names, so no separators and no leading dot."""

ID_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
"""Instance ids: USD prim names."""


class ProxyMesh(NamedTuple):
    """A triangle mesh standing in for a field in tools that cannot evaluate fields."""

    points: np.ndarray
    """(n, 3) float32 vertices in metres (the field's world: the room, or the object's canonical frame)."""
    faces: np.ndarray
    """(m, 3) int32 vertex indices, counter-clockwise seen from outside."""
    colors: np.ndarray | None = None
    """(n, 3) float32 vertex colours in [0, 1], or None."""

    @property
    def extent(self) -> np.ndarray:
        """(2, 3) float32 axis-aligned bounds of the points."""
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)]).astype(np.float32)


@dataclass
class FieldRecord:
    """A field as the stage records it (scene field or library object)."""

    name: str
    """Library name (``dc``) or scene name."""
    label: str
    """Semantic class (``chair``, ``table``; ``scene`` for a room)."""
    checkpoint: Path
    """Absolute path of the checkpoint (.safetensors) on disk."""
    to_world: np.ndarray
    """(4, 4) float64 field frame -> metres (room metres, or the canonical object frame)."""
    bounds: np.ndarray
    """(2, 3) float64 AABB in the field frame."""
    symmetry_order: int
    """Rotational symmetry about +Z: 1 none, k k-fold, 0 continuous."""
    provenance: dict
    """The checkpoint's provenance record (JSON-serialisable)."""
    proxy: ProxyMesh
    """Marching-cubes proxy in metres."""
    source_mesh: SourceMesh | None = None
    """The mesh a library object was distilled from, with its colours or texture (None: none kept)."""


@dataclass
class RegistrationProvenance:
    """How an instance's transform was found (from ``regnf register``)."""

    method: str
    """Registration method, e.g. ``regnf``."""
    confidence: float
    """Fraction of SDF residuals under the inlier threshold."""
    accepted: bool
    """Whether the confidence passed the acceptance threshold."""
    library_name: str
    """The library object that was registered (the instance may since have been swapped)."""
    scene_to_library: np.ndarray
    """(4, 4) float64 T: scene field frame -> library field frame."""
    losses: dict[str, float] = field(default_factory=dict)
    """Final losses and residuals."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage."""
    thresholds: dict[str, float] = field(default_factory=dict)
    """Inlier and acceptance thresholds used."""
    proposal_center: np.ndarray | None = None
    """(3,) float64 proposal box centre in the scene field frame, or None."""
    proposal_half_extents: np.ndarray | None = None
    """(3,) float64 proposal box half sizes, or None."""
    proposal_rotation: np.ndarray | None = None
    """(3, 3) float64 proposal box axes (columns), or None."""
    forced: bool = False
    """Written although not accepted (``force``)."""
    discovery: dict | None = None
    """``regnf discover``'s record (candidate box, objects tried and their confidences); None: box given."""
    warnings: list[str] = field(default_factory=list)
    """What the registration warned of, one line each (a scale that suggests other units)."""


@dataclass
class InstanceRecord:
    """A library object placed in the scene."""

    id: str
    """Prim name under ``/World/Instances``."""
    library_name: str
    """The library object shown (the slot's variant selection)."""
    object_to_scene: np.ndarray
    """(4, 4) float64 canonical object metres -> scene metres (a similarity)."""
    registration: RegistrationProvenance | None = None
    """Provenance of the transform, None when placed by hand."""


@dataclass
class ComposedScene:
    """Everything a stage records.

    With a ``physics_density`` the stage carries ``UsdPhysics``: every instance a rigid body, every
    library mesh a convex-hull collider of that density, the scene a static collider. The
    ``edited_scene`` mesh is the render-purpose mesh other tools show (the proxy keeps the whole
    scene); any change of the instances drops it, as it belongs to the instances it was cut for."""

    scene: FieldRecord
    """The scene field (its proxy in room metres)."""
    library: dict[str, FieldRecord] = field(default_factory=dict)
    """Library objects by name."""
    instances: dict[str, InstanceRecord] = field(default_factory=dict)
    """Instances by id, in insertion order."""
    provenance: dict = field(default_factory=dict)
    """Stage-level provenance (``customLayerData``): strings, numbers, bools, nested dicts."""
    physics_density: float | None = None
    """Density of the library objects for simulators' physics, kg / m^3, or None: no physics."""
    edited_scene: ProxyMesh | None = None
    """The scene less every instance's removal region, room metres (the mesh other tools show), or None."""

    def classes(self) -> dict[str, list[str]]:
        """Library names per class, sorted (the variants of each class's slot)."""
        out: dict[str, list[str]] = {}
        for name, rec in self.library.items():
            out.setdefault(rec.label, []).append(name)
        return {k: sorted(v) for k, v in sorted(out.items())}

    def new_instance_id(self, library_name: str) -> str:
        """A fresh id ``<name>_<k>`` (characters a prim name cannot hold become ``_``)."""
        base = re.sub(r"[^A-Za-z0-9_]", "_", library_name)
        base = base if ID_RE.match(base) else f"i_{base}"
        k = 1
        while f"{base}_{k}" in self.instances:
            k += 1
        return f"{base}_{k}"
