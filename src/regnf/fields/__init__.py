"""Signed-distance fields: the :class:`Field` interface, analytic fields for exact tests, the neural SDF (a dense grid pyramid or hash grid and an MLP), similarities and the one oriented box (:class:`OrientedBox`).

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "Field": "field",
    "FieldInfo": "field",
    "Symmetry": "field",
    "NeuralSDF": "neural_sdf",
    "NeuralSDFConfig": "neural_sdf",
    "OrientedBox": "oriented_box",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .field import Field, FieldInfo, Symmetry
    from .neural_sdf import NeuralSDF, NeuralSDFConfig
    from .oriented_box import OrientedBox
