"""Screening of initial hypotheses by SDF evidence before the (costly) refinement.

ICP's fitness counts scene samples near library samples; for an object seen from one side a
pose that is half a turn off often fits the seen half as well as the true pose does, and ICP
ranks the two alike. The refinement's confidence at a pose, before any step, is the fraction
of inlier SDF residuals in both directions, weighted by where the scene's views observed
space: a flip puts library surface into observed free space and is charged for it
(docs/decisions/registration-initialisation.md). It costs two field queries for all
candidates together, so every ICP result can be screened and only the best few refined.
"""

from __future__ import annotations

import torch

from regnf.fields.field import Field

from .initialisation import Hypothesis
from .refinement import RefineConfig, refine_many, without_steps


def screen_hypotheses(
    scene_field: Field,
    library_field: Field,
    A: torch.Tensor,
    B: torch.Tensor,
    hypotheses: list[Hypothesis],
    config: RefineConfig,
    keep: int,
    workers: int | None = None,
) -> list[Hypothesis]:
    """The ``keep`` hypotheses with the highest SDF confidence at their pose, best first.

    Parameters
    ----------
    scene_field, library_field : Field
        On the device of ``A`` and ``B``.
    A : (n, 3) float
        Scene surface samples, scene field frame.
    B : (m, 3) float
        Library surface samples, library field frame.
    hypotheses : list of Hypothesis
        Candidates (from :func:`regnf.registration.initialisation.initial_hypotheses`).
    config : RefineConfig
        The refinement's settings (inlier threshold, visibility weighting); no step is taken.
    keep : int
        Hypotheses returned at most.
    workers : int, optional
        CPU threads of the two field queries (:func:`~regnf.registration.refinement.refine_many`).

    Returns
    -------
    list of Hypothesis
        Sorted by screened confidence, then by ICP fitness; ties keep the input order.
    """
    if len(hypotheses) <= 1:
        return list(hypotheses[:keep])
    scores = refine_many(scene_field, library_field, A, B, [h.transform for h in hypotheses],
                         without_steps(config), workers=workers)
    order = sorted(range(len(hypotheses)),
                   key=lambda i: (-round(scores[i].inlier_fraction, 6), -hypotheses[i].fitness, i))
    return [hypotheses[i] for i in order[:keep]]
