"""Containment: how much of the registered library object lies inside its proposal box.

A proposal says where the object is; the SDF confidence says how well the two surfaces agree
where there are samples, but its sample sets grow only where they agree (the refinement's
resampling keeps a new sample only when both fields put it on their surface), so a wrong
object can score well on the part it explains and say nothing about the rest. Containment
asks the question the box answers: what fraction of the library's own surface, mapped into the
scene, falls inside the box the scene was sampled in.

A right pair's winner lies wholly inside its box; a wrong object whose fit explains part of the
box leaves much of itself outside (docs/decisions/registration-acceptance.md).
"""

from __future__ import annotations

import numpy as np

from regnf.core.errors import RegnfError
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.transform import SimilarityTransform


def containment(library_points: np.ndarray, transform: SimilarityTransform, region: OrientedBox) -> float:
    """Fraction of library surface points that ``transform`` maps into ``region``.

    Parameters
    ----------
    library_points : (m, 3) float
        Points spread over the library object's surface, library field frame (m >= 1).
    transform : SimilarityTransform
        Scene field frame -> library field frame, ``y = s R x + t``.
    region : OrientedBox
        Where the object must lie, scene field frame.

    Returns
    -------
    float
        In [0, 1].
    """
    Y = np.asarray(library_points, dtype=np.float64)
    if Y.ndim != 2 or Y.shape[1] != 3 or len(Y) == 0:
        raise RegnfError(f"library_points must be a non-empty (m, 3) array, got shape {Y.shape}")
    return float(region.contains(transform.inverse().apply(Y)).mean())
