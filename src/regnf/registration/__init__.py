"""Registration: the 7-DoF similarity (rotation, translation, scale) that maps a scene field's
frame onto a library object's field frame, found inside a proposal box (:func:`register`) or,
with no boxes, for every library object standing in the scene (:func:`discover`), and its
errors against ground truth (:func:`registration_errors`).

Names load their module on first use (:mod:`regnf.core.lazy_exports`), so that the metrics do
not load Open3D.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "register": "pipeline",
    "discover": "discovery",
    "DiscoveryConfig": "discovery",
    "DiscoveryResult": "discovery",
    "FieldFiles": "discovery",
    "RegistrationConfig": "pipeline",
    "RegistrationResult": "result",
    "OrientedBox": "regnf.fields.oriented_box",
    "SimilarityTransform": "transform",
    "registration_errors": "metrics",
    "RegistrationErrors": "metrics",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from regnf.fields.oriented_box import OrientedBox

    from .discovery import DiscoveryConfig, DiscoveryResult, FieldFiles, discover
    from .metrics import RegistrationErrors, registration_errors
    from .pipeline import RegistrationConfig, register
    from .result import RegistrationResult
    from .transform import SimilarityTransform
