"""The registration methods by name: ours, its ablations and the baselines, behind one signature.

A method is a function ``(scene, library, proposal, config, hints) -> RegistrationResult``
(:data:`RegistrationMethod`); :data:`METHODS` names every one the benchmarks compare, in the
order of their tables. A new method is a function of that signature and one line in
:data:`METHODS` (docs/design.md, "A new registration method"); ``regnf bench registration``
then runs it on every pair and reports it with the same metrics as the others.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.baselines import register_fgr, register_init_only, register_nerf2nerf
from regnf.registration.pipeline import (
    RegistrationConfig,
    adam_method,
    paper_method,
    register,
    single_hypothesis,
)
from regnf.registration.result import RegistrationResult
from regnf.registration.transform import SimilarityTransform


class PairHints(NamedTuple):
    """What a benchmark knows about a pair beyond a method's inputs; only oracle baselines read it."""

    truth: SimilarityTransform | None = None
    """The true transform (scene field -> library field), None for a pair with no true pose."""
    library_surface: np.ndarray | None = None
    """(n, 3) float: points on the library object's true surface, library field frame."""
    seed: int = 0
    """Seed of a method's own random draws."""


RegistrationMethod = Callable[[Field, Field, OrientedBox, RegistrationConfig, PairHints], RegistrationResult]
"""``(scene, library, proposal, config, hints) -> RegistrationResult``."""

METHODS: dict[str, RegistrationMethod] = {
    "regnf": lambda s, lib, box, cfg, h: register(s, lib, box, cfg),
    "regnf-adam": lambda s, lib, box, cfg, h: register(s, lib, box, adam_method(cfg), method="regnf-adam"),
    "regnf-single": lambda s, lib, box, cfg, h: register(s, lib, box, paper_method(cfg), method="regnf-single"),
    "regnf-k1": lambda s, lib, box, cfg, h: register(s, lib, box, single_hypothesis(cfg), method="regnf-k1"),
    "regnf-init": lambda s, lib, box, cfg, h: register_init_only(s, lib, box, cfg),
    "fgr": lambda s, lib, box, cfg, h: register_fgr(s, lib, box, cfg),
    "nerf2nerf": lambda s, lib, box, cfg, h: register_nerf2nerf(s, lib, box, cfg, h.truth, h.library_surface,
                                                                seed=h.seed),
}
"""Every method by name. ``regnf``: ours. Baselines: ``regnf-single`` (Reg-NF as published: one
hypothesis, the paper's refinement), ``regnf-init`` (our initialisation alone), ``fgr``,
``nerf2nerf`` (initialised from perturbed true keypoints: an oracle, it reads ``hints``).
Ablations: ``regnf-adam`` (ours with the paper's Adam refinement instead of
Levenberg-Marquardt), ``regnf-k1`` (ours with only the best initial hypothesis refined)."""
