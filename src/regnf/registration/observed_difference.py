"""How much of what tells two registered library objects apart the scene's views observed:
discovery leaves a candidate unmatched when the two best objects differ only where no view
looked (:attr:`regnf.registration.discovery.DiscoveryConfig.unobserved_difference`)."""

from __future__ import annotations

import numpy as np
import torch

from regnf.fields.field import Field
from regnf.registration.result import RegistrationResult

DIFFERENCE_TOLERANCE = 0.01
"""Surface farther than this fraction of the object's diagonal from the other shape is where two
shapes differ."""

UNOBSERVED = 0.05
"""Below this share the views saw (next to) nothing of what tells two objects apart: the wrong
one fits the observed evidence as well as the right one."""


def observed_share(scene_field: Field, points: np.ndarray) -> float:
    """Mean observation weight of ``points`` in the scene's visibility grid.

    Parameters
    ----------
    scene_field : Field
        Its ``visibility`` grid is read (None: everything counts as observed).
    points : (n, 3) float
        Points in the scene field's frame: where two shapes differ.

    Returns
    -------
    float
        In [0, 1]; 1 without a visibility grid; nan for no points (the shapes do not differ).
    """
    if len(points) == 0:
        return float("nan")
    if scene_field.visibility is None:
        return 1.0
    x = torch.as_tensor(np.asarray(points), dtype=torch.float32, device=scene_field.device)
    return float(scene_field.visibility.observed(x).mean())


def observed_difference(scene_field: Field, field_a: Field, result_a: RegistrationResult, field_b: Field,
                        result_b: RegistrationResult, tolerance: float = DIFFERENCE_TOLERANCE) -> float:
    """How much of what tells two registered library objects apart the scene's views observed.

    Each object's library samples are placed at its registered pose; those farther from the
    other object's surface (its SDF there, in scene field units) than ``tolerance`` times the
    diagonal are where the two differ, and the scene's visibility grid is read there.

    Returns
    -------
    float
        :func:`observed_share` of the differing surface.
    """
    placed = [r.transform.inverse().apply(np.asarray(r.samples[1], dtype=np.float64)) for r in (result_a, result_b)]
    parts = []
    diag = float(np.linalg.norm(placed[0].max(axis=0) - placed[0].min(axis=0)))
    for points, other, result in ((placed[0], field_b, result_b), (placed[1], field_a, result_a)):
        x = torch.as_tensor(result.transform.apply(points), dtype=torch.float32, device=other.device)
        with torch.no_grad():
            distance = other.sdf(x).abs().double().cpu().numpy().reshape(-1) / result.transform.s
        parts.append(points[distance > tolerance * diag])
    return observed_share(scene_field, np.concatenate(parts))
