"""Every registration method by name, through the one signature, on an analytic scene."""

from __future__ import annotations

import numpy as np

from regnf.registration.methods import METHODS, PairHints
from regnf.registration.pipeline import RegistrationConfig

from .test_pipeline import errors, library_at_scale, scene_and_truth


def test_each_method_answers_through_the_seam_and_says_which_it_is() -> None:
    scene, proposal, truth = scene_and_truth(1.0, 1.0)
    lib = library_at_scale(1.0)
    # nerf2nerf's keypoints come from these library points (the corners of the base slab).
    surface = np.array([[x, y, z] for x in (-0.4, 0.4) for y in (-0.25, 0.25) for z in (0.0, 0.1)])
    hints = PairHints(truth, surface, seed=0)
    cfg = RegistrationConfig()
    for name, method in METHODS.items():
        result = method(scene, lib, proposal, cfg, hints)
        assert result.method == name, (name, result.method)
        assert 0.0 <= result.confidence <= 1.0
        if name in ("regnf", "regnf-k1", "regnf-single"):  # the full methods find the true pose
            r, t, s = errors(result.transform, truth)
            assert r < 0.02 and t < 0.01 and s < 0.01, (name, r, t, s)
