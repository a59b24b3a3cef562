"""What a capture observed: each frame's rays (lenses), the depth samples training draws from (:func:`build_samples`) with their memory estimate, and the space the views saw (:class:`VisibilityGrid`).

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "RGBDSamples": "rgbd_samples",
    "build_samples": "rgbd_samples",
    "VisibilityGrid": "visibility",
    "build_visibility": "visibility",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .rgbd_samples import RGBDSamples, build_samples
    from .visibility import VisibilityGrid, build_visibility
