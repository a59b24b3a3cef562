"""An object instance placed in a room: which library object, where, and its box."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from regnf.core.errors import RegnfError


@dataclass
class Instance:
    """One placed object; poses map canonical object metres to room metres."""

    id: str
    """Unique id in its room, for example ``dc_0``."""
    library: str
    """Library object name (``dc``), or the dataset's own name for a loaded capture."""
    label: str
    """Semantic class, ``chair`` or ``table``."""
    object_to_world: np.ndarray
    """(4, 4) float64: canonical object metres -> room metres (scale, yaw about z, translation)."""
    scale: float = 1.0
    """Uniform scale inside ``object_to_world`` (1.0: library objects are metric)."""
    yaw: float = 0.0
    """Rotation about +Z in radians."""
    box_corners: np.ndarray | None = None
    """(8, 3) float64 corners of the object's oriented bounding box in room metres."""
    mesh_path: Path | None = None
    """Mesh of the instance in room metres, if stored on disk (captures)."""

    def __post_init__(self) -> None:
        self.object_to_world = np.asarray(self.object_to_world, dtype=np.float64)
        if self.object_to_world.shape != (4, 4):
            raise RegnfError(
                f"instance {self.id!r}: object_to_world must be 4x4, "
                f"got {self.object_to_world.shape}"
            )
        if self.box_corners is not None:
            self.box_corners = np.asarray(self.box_corners, dtype=np.float64)
            if self.box_corners.shape != (8, 3):
                raise RegnfError(
                    f"instance {self.id!r}: box_corners must be 8x3, got {self.box_corners.shape}"
                )

    def to_json(self, mesh_path: str | None = None) -> dict:
        """The ``instances`` entry of ``meta_data.json`` (metres)."""
        return {
            "id": self.id,
            "library": self.library,
            "class": self.label,
            "object_to_world": self.object_to_world.tolist(),
            "scale": float(self.scale),
            "yaw": float(self.yaw),
            "box_corners": None if self.box_corners is None else self.box_corners.tolist(),
            "mesh_path": mesh_path,
        }


def box_corners(bounds: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Corners of an axis-aligned box mapped by a 4x4 transform.

    Parameters
    ----------
    bounds : (2, 3) float
        Box min and max in the source frame.
    transform : (4, 4) float
        Source -> destination.

    Returns
    -------
    (8, 3) float64
        Corners in the destination frame, in ``itertools.product`` order of (x, y, z) choosing
        min (0) or max (1).
    """
    idx = np.array(list(itertools.product((0, 1), repeat=3)))
    corners = bounds[idx, [0, 1, 2]]
    return corners @ transform[:3, :3].T + transform[:3, 3]


def yaw_pose(yaw: float, translation: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(4, 4) float64 similarity: scale, then rotation by ``yaw`` about +Z, then translation."""
    # Written out rather than scipy's Rotation.from_euler, which differs in the last bits: the
    # rooms' geometry, and so every cached capture, stays bit-identical.
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = scale * np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pose[:3, 3] = translation
    return pose
