"""Field checkpoints: :func:`save_field` and :func:`load_field` (safetensors with a JSON header), their checks and content digest.

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "load_field": "checkpoint",
    "save_field": "checkpoint",
    "CheckpointError": "checkpoint_checks",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .checkpoint import load_field, save_field
    from .checkpoint_checks import CheckpointError
