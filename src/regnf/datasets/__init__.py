"""Synthetic data sets from a stage: :func:`generate` renders seeded variants (random instance replacement) to nerfstudio, COCO and BOP folders, with a manifest that makes runs resumable.

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "generate": "generation",
    "GenerateConfig": "generate_config",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .generate_config import GenerateConfig
    from .generation import generate
