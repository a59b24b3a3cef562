"""Seen free: how much of the registered library object lies where the scene's views saw nothing.

The SDF confidence counts a library sample that lands in empty space as an outlier, like one
that lands a little off the surface; but the two say different things. A sample a few
millimetres off is a fit's imprecision; a sample centimetres in front of every surface, in
space the scene's training views observed, is matter the pose puts where the views saw none:
evidence against the pose, not a lack of evidence for it. A wrong object can fit the part of
a box the views saw well and put the rest of itself in space no view saw (where nothing
contradicts it) and in space they saw empty (where everything does).

:func:`seen_free_fraction` is the share of the library's surface samples, among those the
pose puts in observed space (weighted by the visibility grid), whose scene SDF exceeds a
margin: the fraction of the object's observed part that stands in free space. The
confidence is multiplied by one less it (:func:`regnf.registration.pipeline.scored`).

A wrong object that fits part of a box puts a large share of its observed samples in seen free
space, a right pair almost none (docs/decisions/registration-acceptance.md).
"""

from __future__ import annotations

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.registration.transform import SimilarityTransform


def seen_free_fraction(scene_field: Field, library_points: np.ndarray, transform: SimilarityTransform,
                       margin_m: float) -> float:
    """Fraction of the observed library samples that ``transform`` puts in seen free space.

    Parameters
    ----------
    scene_field : Field
        The scene; its ``visibility`` weighs each sample (None: everything observed).
    library_points : (m, 3) float
        Points spread over the library object's surface, library field frame (m >= 1).
    transform : SimilarityTransform
        Scene field frame -> library field frame, ``y = s R x + t``.
    margin_m : float
        A sample counts as in free space where the scene's SDF exceeds this, metres.

    Returns
    -------
    float
        In [0, 1]; 0 when no sample lands in observed space.
    """
    Y = np.asarray(library_points, dtype=np.float64)
    if Y.ndim != 2 or Y.shape[1] != 3 or len(Y) == 0:
        raise RegnfError(f"library_points must be a non-empty (m, 3) array, got shape {Y.shape}")
    x = torch.as_tensor(transform.inverse().apply(Y), dtype=torch.float32, device=scene_field.device)
    with torch.no_grad():
        distance = scene_field.sdf_chunked(x).reshape(-1) * float(scene_field.world_scale)
        weight = (scene_field.visibility.observed(x) if scene_field.visibility is not None
                  else torch.ones_like(distance))
    observed = float(weight.sum())
    if observed <= 1e-6:
        return 0.0
    return float((weight * (distance > margin_m).to(weight.dtype)).sum()) / observed
