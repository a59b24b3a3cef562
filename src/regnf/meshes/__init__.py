"""Meshes in and out of fields: reading and repairing meshes, their inside and outside (winding numbers), the source mesh kept beside a distilled field, and meshing a field (:func:`extract_mesh`).

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "extract_mesh": "meshing",
    "load_mesh_file": "mesh_reading",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .mesh_reading import load_mesh_file
    from .meshing import extract_mesh
