"""Baselines run through the same sampling and metrics as Reg-NF (the paper's Table I rows).

- ``regnf-init``: our initialisation alone (best FPFH + RANSAC + ICP hypothesis).
- ``fgr``: Open3D's Fast Global Registration on the same clouds and features; FGR estimates a
  rigid transform, the scale is our pre-estimate (ratio of the clouds' radii).
- ``nerf2nerf``: one-directional SDF residual (scene samples only), scale fixed at 1,
  initialised from a few ground-truth keypoint correspondences perturbed by Gaussian noise
  (the paper hand-picked keypoints; we pick ``n_keypoints`` spread-out surface points of the
  library object and perturb their scene positions by ``keypoint_noise_rel`` times the
  object's diagonal), solved rigidly (Kabsch, s = 1) and refined.

Each returns a :class:`RegistrationResult` whose confidence is measured the same way as
Reg-NF's: the fraction of SDF residuals under the inlier threshold at the returned transform,
times the fraction of the library object inside the proposal, times one less the fraction of its
observed part in seen free space (:func:`regnf.registration.pipeline.scored`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.initialisation import Hypothesis, fgr_baseline
from regnf.registration.pipeline import (
    RegistrationConfig,
    check_fields,
    initialise,
    sample_pair,
    sample_tensors,
    scored,
)
from regnf.registration.ransac import fit_similarities
from regnf.registration.refinement import RefineResult, refine, without_steps
from regnf.registration.result import HypothesisReport, RegistrationResult
from regnf.registration.sampling import SurfaceSamples
from regnf.registration.transform import SimilarityTransform


def _result(method: str, T: SimilarityTransform, evaluated: RefineResult, cfg: RegistrationConfig,
            proposal: OrientedBox, timings: dict, *, scene: Field, samples: tuple[np.ndarray, np.ndarray],
            fitness: float = float("nan"), initial: SimilarityTransform | None = None) -> RegistrationResult:
    confidence, inside, free = scored(evaluated, samples[1], proposal, cfg, scene)
    return RegistrationResult(
        samples=samples,
        transform=T,
        confidence=float(confidence),
        accepted=bool(confidence >= cfg.acceptance_threshold),
        method=method,
        losses={"loss": float(evaluated.loss), "mean_residual_scene": float(evaluated.mean_residual_A),
                "mean_residual_library": float(evaluated.mean_residual_B),
                "iterations": float(evaluated.iterations),
                "inlier_fraction": float(evaluated.inlier_fraction), "containment": float(inside),
                "seen_free": float(free)},
        timings=timings,
        hypotheses=[HypothesisReport(initial or T, T, fitness, float(evaluated.loss), float(confidence))],
        proposal=proposal,
        thresholds={"acceptance_threshold": cfg.acceptance_threshold,
                    "inlier_threshold": cfg.refine.inlier_threshold},
        history=list(evaluated.history),
    )


def _score(scene: Field, library: Field, A, B, T: SimilarityTransform, cfg: RegistrationConfig) -> RefineResult:
    """Residuals and confidence at ``T`` without moving it (zero refinement steps)."""
    return refine(scene, library, A, B, T, without_steps(cfg.refine))


def _one_hypothesis(method: str, scene: Field, library: Field, proposal: OrientedBox,
                    cfg: RegistrationConfig, make: Callable[[SurfaceSamples, SurfaceSamples], Hypothesis],
                    ) -> RegistrationResult:
    """Sample, make one hypothesis with ``make``, score it without refining."""
    check_fields(scene, library)
    t0 = time.perf_counter()
    ss, ls = sample_pair(scene, library, proposal, cfg)
    t1 = time.perf_counter()
    hyp = make(ss, ls)
    t2 = time.perf_counter()
    A, B = sample_tensors(ss, ls, library.device)
    timings = {"sampling": t1 - t0, "initialisation": t2 - t1, "total": t2 - t0}
    return _result(method, hyp.transform, _score(scene, library, A, B, hyp.transform, cfg),
                   cfg, proposal, timings, fitness=float(hyp.fitness), scene=scene,
                   samples=(ss.points, ls.points))


def register_init_only(scene: Field, library: Field, proposal: OrientedBox,
                       config: RegistrationConfig | None = None) -> RegistrationResult:
    """Reg-NF-init: the best initial hypothesis, not refined."""
    cfg = config or RegistrationConfig()
    one = dataclasses.replace(cfg, init=dataclasses.replace(cfg.init, top_k=1))
    return _one_hypothesis("regnf-init", scene, library, proposal, cfg,
                           lambda ss, ls: initialise(scene, library, proposal, ss, ls, one)[0])


def register_fgr(scene: Field, library: Field, proposal: OrientedBox,
                 config: RegistrationConfig | None = None) -> RegistrationResult:
    """FGR on the same samples and features (rigid; scale from the radius pre-estimate)."""
    cfg = config or RegistrationConfig()
    return _one_hypothesis("fgr", scene, library, proposal, cfg,
                           lambda ss, ls: fgr_baseline(ss, ls, cfg.init))


def spread_keypoints(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` mutually distant points (farthest-point sampling from the first point)."""
    chosen = [0]
    d = np.linalg.norm(points - points[0], axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(points - points[i], axis=1))
    return points[chosen]


def kabsch(src: np.ndarray, dst: np.ndarray) -> SimilarityTransform:
    """The rigid transform (s = 1) that best maps ``src`` (n, 3) onto ``dst`` (n, 3): the
    rotation of the best similarity (its scale does not change it), the translation of the
    centroids."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    R = fit_similarities(src[None], dst[None])[0][0]
    return SimilarityTransform(R, dst.mean(0) - R @ src.mean(0), 1.0)


def register_nerf2nerf(scene: Field, library: Field, proposal: OrientedBox,
                       config: RegistrationConfig | None, truth: SimilarityTransform,
                       library_surface: np.ndarray, n_keypoints: int = 4,
                       keypoint_noise_rel: float = 0.02, seed: int = 0) -> RegistrationResult:
    """nerf2nerf-style: keypoint initialisation, one-directional residual, scale fixed at 1.

    Parameters
    ----------
    truth : SimilarityTransform
        Ground-truth scene -> library transform (stands in for the hand-picked keypoints).
    library_surface : (n, 3) float
        Surface points of the library object in its field frame; keypoints are picked here.
    keypoint_noise_rel : float
        Std of the Gaussian noise on each keypoint's scene position, as a fraction of the
        object's diagonal (0.02: a careful human click).
    """
    cfg = config or RegistrationConfig()
    check_fields(scene, library)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    ss, ls = sample_pair(scene, library, proposal, cfg)
    t1 = time.perf_counter()
    kp_lib = spread_keypoints(np.asarray(library_surface, dtype=np.float64), n_keypoints)
    kp_scene = truth.inverse().apply(kp_lib)
    diag_scene = float(np.linalg.norm(np.ptp(truth.inverse().apply(library_surface), axis=0)))
    kp_scene = kp_scene + rng.normal(0.0, keypoint_noise_rel * diag_scene, kp_scene.shape)
    T0 = kabsch(kp_scene, kp_lib)
    A, _ = sample_tensors(ss, ss, library.device)
    n2n = dataclasses.replace(cfg.refine, bidirectional=False, fix_scale=True, optimizer="adam")
    res = refine(scene, library, A, None, T0, n2n)
    t2 = time.perf_counter()
    timings = {"sampling": t1 - t0, "initialisation": 0.0, "refinement": t2 - t1, "total": t2 - t0}
    return _result("nerf2nerf", res.transform, res, cfg, proposal, timings, initial=T0, scene=scene,
                   samples=(ss.points, ls.points))
