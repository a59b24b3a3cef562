"""Training fields: NeuS-style fields from posed RGB-D captures (:func:`train_rgbd`) or distilled from meshes (:func:`distill_mesh`), the presets, the optimiser and the per-frame pose refinement.

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "RGBDTrainConfig": "training",
    "train_rgbd": "training",
    "DistillConfig": "distill",
    "distill_mesh": "distill",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .distill import DistillConfig, distill_mesh
    from .training import RGBDTrainConfig, train_rgbd
