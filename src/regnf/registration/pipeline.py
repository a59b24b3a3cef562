"""``register``: the 7-DoF similarity of a library object inside a scene field (Reg-NF).

Stages (docs/design.md sections 1.2-1.5), each a function with its own config:

1. multi-view surface sampling of the scene inside the proposal box and of the whole
   library object (:mod:`regnf.registration.sampling`);
2. scale-aware FPFH + RANSAC + ICP, joined by ICP from a sweep of upright yaws when the
   object stands as its library model does (:mod:`regnf.registration.initialisation`,
   :mod:`regnf.registration.upright`); the distinct results are screened by their SDF evidence at
   the pose and the best K kept (:mod:`regnf.registration.screening`);
3. bidirectional SDF refinement with the adaptive robust loss
   (:mod:`regnf.registration.refinement`): the best screened hypothesis first, and the others
   unless it is confident already (``RegistrationConfig.confident_score``); the one with the
   most inlier residuals wins (the final NLLs are not comparable: each hypothesis learns its own
   kernel shape and scale).

The result carries a confidence (the fraction of SDF residuals under a threshold, both
directions, times the fraction of the library object that lies in the proposal box,
:mod:`regnf.registration.containment`) so that a failed registration, or the wrong object, is
reported, not silently written.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.core.threads import map_one_thread_each, one_thread, worker_count
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.containment import containment
from regnf.registration.free_space import seen_free_fraction
from regnf.registration.initialisation import (
    Hypothesis,
    InitConfig,
    NoHypothesisError,
    ObjectSymmetry,
    centroid_hypothesis,
    initial_hypotheses,
)
from regnf.registration.metrics import symmetry_axis
from regnf.registration.refinement import RefineConfig, RefineResult, refine_many
from regnf.registration.result import HypothesisReport, RegistrationResult
from regnf.registration.sampling import SamplingConfig, SurfaceSamples, sample_surface
from regnf.registration.screening import screen_hypotheses
from regnf.registration.transform import SimilarityTransform
from regnf.registration.upright import UprightPrior


@dataclass
class RegistrationConfig:
    """Every setting of :func:`register`; defaults are the paper's values where it gives one."""

    scene_sampling: SamplingConfig = field(default_factory=SamplingConfig)
    """Multi-view sampling of the scene inside the proposal box."""
    library_sampling: SamplingConfig = field(default_factory=SamplingConfig)
    """Multi-view sampling of the whole library object."""
    init: InitConfig = field(default_factory=InitConfig)
    """FPFH + RANSAC + ICP initialisation (its ``top_k`` hypotheses are refined)."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Bidirectional refinement."""
    upright: bool = True
    """The object stands as its library model does (``scene_sampling.up`` is its +Z); False: RANSAC's starts only."""
    acceptance_threshold: float = 0.6
    """A result whose confidence is below this is reported as a failed registration."""
    free_space_margin_m: float = 0.02
    """Seen-free-space margin in front of the scene's surface, metres; inf: never (docs/decisions/registration-acceptance.md)."""
    confident_score: float = 0.85
    """Confidence at which the first hypothesis spares the rest; > 1: refine all (docs/decisions/registration-acceptance.md)."""
    device: str | None = None
    """Torch device of the fields; None: the scene field's device."""

    def __post_init__(self) -> None:
        if not self.free_space_margin_m > 0:  # NaN fails too
            raise RegnfError(f"free_space_margin_m must be > 0 metres (inf: never charged), "
                             f"got {self.free_space_margin_m}")


def check_fields(scene: Field, library: Field) -> None:
    """Raise a clear error when the two fields cannot be registered together."""
    for name, f in (("scene", scene), ("library", library)):
        if not isinstance(f, Field):
            raise TypeError(f"the {name} field must be a regnf.fields.Field, got {type(f).__name__}")
    if scene.device != library.device:
        raise RegnfError(
            f"the scene field is on {scene.device} and the library field on {library.device}; "
            "move both to one device (field.to(device))"
        )


def sample_pair(
    scene_field: Field, library_field: Field, proposal: OrientedBox, config: RegistrationConfig,
    workers: int | None = None,
) -> tuple[SurfaceSamples, SurfaceSamples]:
    """Stage 1: the scene's surface inside the proposal and the whole library object's.

    The two are independent torch work, so they run side by side, each on one CPU thread
    (:func:`~regnf.core.threads.map_one_thread_each`, ``workers`` threads: default one per
    core the caller's torch may use): the same bits as one after the other, on any machine.
    """
    jobs = [(scene_field, proposal, config.scene_sampling, "scene"),
            (library_field, None, config.library_sampling, "library")]
    scene, library = map_one_thread_each(lambda job: sample_surface(*job[:3], side=job[3]), jobs, workers)
    return scene, library


def library_symmetry(library_field: Field) -> ObjectSymmetry:
    """The declared symmetry of a library field, its axis in the library field frame."""
    W = library_field.to_world.detach().cpu().double().numpy()
    return ObjectSymmetry(int(library_field.info.symmetry.order), symmetry_axis(W))


def upright_prior(scene_field: Field, library_field: Field, proposal: OrientedBox,
                  config: RegistrationConfig) -> UprightPrior | None:
    """The up axes of both frames and the box centre, or None when ``config.upright`` is off."""
    if not config.upright:
        return None
    W = library_field.to_world.detach().cpu().double().numpy()
    return UprightPrior(np.asarray(config.scene_sampling.up, dtype=np.float64), symmetry_axis(W),
                        np.asarray(proposal.center, dtype=np.float64))


def hypotheses_or_fallback(
    scene: SurfaceSamples, library: SurfaceSamples, config: InitConfig,
    symmetry: ObjectSymmetry | None = None, upright: UprightPrior | None = None,
    limit: int | None = None, workers: int = 1,
) -> list[Hypothesis]:
    """Stage 2, or the centroid start when RANSAC finds nothing, so that the refinement
    runs and a low confidence (not an exception) reports the failed registration."""
    try:
        return initial_hypotheses(scene, library, config, symmetry, upright, limit, workers)
    except NoHypothesisError:
        return [centroid_hypothesis(scene, library, config)]


def initialise(scene_field: Field, library_field: Field, proposal: OrientedBox, scene: SurfaceSamples,
               library: SurfaceSamples, config: RegistrationConfig, workers: int | None = None) -> list[Hypothesis]:
    """Stage 2: up to ``config.init.top_k`` hypotheses, best first.

    RANSAC's and the upright sweep's ICP results (``config.init.candidates`` distinct ones at
    most), screened by their SDF evidence at the pose (:func:`screen_hypotheses`, its field
    queries on ``workers`` threads).
    """
    hyps = hypotheses_or_fallback(scene, library, config.init, library_symmetry(library_field),
                                  upright_prior(scene_field, library_field, proposal, config),
                                  limit=config.init.candidates, workers=worker_count(workers))
    A, B = sample_tensors(scene, library, library_field.device)
    return screen_hypotheses(scene_field, library_field, A, B, hyps, config.refine, config.init.top_k, workers)


def object_region(proposal: OrientedBox, config: RegistrationConfig) -> OrientedBox:
    """The box the registered object must lie in: the proposal as the scene was sampled in it
    (grown by ``config.scene_sampling.box_inflate``)."""
    return proposal.inflated(config.scene_sampling.box_inflate)


def scored(refined: RefineResult, library_points: np.ndarray, proposal: OrientedBox,
           config: RegistrationConfig, scene_field: Field) -> tuple[float, float, float]:
    """(confidence, containment, seen free) of a refined hypothesis.

    The confidence is the SDF evidence (``refined.inlier_fraction``) times the containment, the
    fraction of ``library_points`` (m, 3), library field frame, that the transform maps into
    :func:`object_region`, times one less the fraction of the observed ones it puts in seen
    free space (:func:`~regnf.registration.free_space.seen_free_fraction`): a right pose of the
    right object satisfies all three, a wrong object that explains part of the box leaves the
    rest of itself outside it or where the scene's views saw nothing.
    """
    inside = containment(library_points, refined.transform, object_region(proposal, config))
    free = (seen_free_fraction(scene_field, library_points, refined.transform, config.free_space_margin_m)
            if math.isfinite(config.free_space_margin_m) else 0.0)
    return refined.inlier_fraction * inside * (1.0 - free), inside, free


def sample_tensors(
    scene: SurfaceSamples, library: SurfaceSamples, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """The sample points as float32 tensors on ``device`` (the refinement's A and B)."""
    A = torch.as_tensor(scene.points, dtype=torch.float32, device=device)
    B = torch.as_tensor(library.points, dtype=torch.float32, device=device)
    return A, B


def register(
    scene_field: Field,
    library_field: Field,
    proposal: OrientedBox,
    config: RegistrationConfig | None = None,
    method: str = "regnf",
    initial: SimilarityTransform | None = None,
    library_samples: SurfaceSamples | None = None,
) -> RegistrationResult:
    """Register ``library_field`` to the object inside ``proposal`` of ``scene_field``.

    Parameters
    ----------
    scene_field, library_field : Field
        On the same device.
    proposal : OrientedBox
        Oriented box around the object, in the scene field's frame.
    config : RegistrationConfig
    method : str
        The name the result reports.
    initial : SimilarityTransform, optional
        A start given by the caller (scene field -> library field; for example a pose a user
        dragged near its place): the refinement starts from it alone, without the
        initialisation's hypotheses. The sampling, refinement and confidence are the same.
    library_samples : SurfaceSamples, optional
        The library field's samples, taken earlier with ``config.library_sampling`` (they do
        not depend on the scene): reused instead of sampled again (discovery registers each
        library object in several boxes).

    Returns
    -------
    RegistrationResult
        ``transform`` maps scene field points to library field points.
    """
    cfg = config or RegistrationConfig()
    check_fields(scene_field, library_field)
    timings: dict[str, float] = {}
    workers = worker_count()  # before one_thread() below sets torch's count to 1
    t0 = time.perf_counter()
    # One thread a computation for sampling and initialisation too (the refinement runs on
    # one): their float sums and Open3D's parallel ICP come out differently on other thread
    # counts, and the screening's ranking turns such last bits into other hypotheses
    # (regnf.core.threads).
    with one_thread():
        if library_samples is None:
            scene_samples, lib_samples = sample_pair(scene_field, library_field, proposal, cfg, workers)
        else:
            scene_samples = sample_surface(scene_field, proposal, cfg.scene_sampling, side="scene")
            lib_samples = library_samples
        timings["sampling"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        if initial is None:
            hyps = initialise(scene_field, library_field, proposal, scene_samples, lib_samples, cfg, workers)
        else:
            hyps = [Hypothesis(initial, float("nan"), float("nan"))]
        timings["initialisation"] = time.perf_counter() - t1
    return refine_hypotheses(scene_field, library_field, proposal, scene_samples, lib_samples, hyps,
                             cfg, method, timings)


def refine_hypotheses(
    scene_field: Field,
    library_field: Field,
    proposal: OrientedBox,
    scene_samples: SurfaceSamples,
    lib_samples: SurfaceSamples,
    hypotheses: list[Hypothesis],
    config: RegistrationConfig,
    method: str = "regnf",
    timings: dict[str, float] | None = None,
) -> RegistrationResult:
    """Stage 3 of :func:`register`: refine ``hypotheses`` and keep the best-scored one.

    The first hypothesis (the screening's best) is refined alone first: when its confidence
    reaches ``config.confident_score``, the others are left unrefined (and unreported);
    otherwise they are refined together and every one competes.

    For callers that sampled and initialised themselves (discovery samples a candidate's box
    once for every library object it tries). ``timings`` holds the earlier stages' seconds;
    ``refinement`` is added and ``total`` is their sum.
    """
    timings = dict(timings or {})
    A, B = sample_tensors(scene_samples, lib_samples, library_field.device)
    t2 = time.perf_counter()
    symmetry = library_symmetry(library_field)
    inits = [h.transform for h in hypotheses]
    # The adaptive NLL is not comparable across hypotheses (each learns its own alpha and c),
    # so rank by what is: the SDF evidence (the fraction of inlier residuals) times the fraction
    # of the library object that lies in the proposal times one less its share in seen free
    # space, then the mean residual.
    refined = refine_many(scene_field, library_field, A, B, inits[:1], config.refine, symmetry=symmetry)
    ranked = [scored(refined[0], lib_samples.points, proposal, config, scene_field)]
    if len(inits) > 1 and ranked[0][0] < config.confident_score:
        more = refine_many(scene_field, library_field, A, B, inits[1:], config.refine, symmetry=symmetry)
        refined += more
        ranked += [scored(r, lib_samples.points, proposal, config, scene_field) for r in more]
    hypotheses = hypotheses[:len(refined)]
    timings["refinement"] = time.perf_counter() - t2
    timings["total"] = sum(v for k, v in timings.items() if k != "total")
    score, inside, free = zip(*ranked)
    reports = [
        HypothesisReport(h.transform, r.transform, float(h.fitness), float(r.loss), float(sc))
        for h, r, sc in zip(hypotheses, refined, score)
    ]
    order = sorted(
        range(len(refined)),
        key=lambda i: (-score[i], refined[i].mean_residual_A + refined[i].mean_residual_B),
    )
    reports = [reports[i] for i in order]
    best, confidence = refined[order[0]], score[order[0]]
    return RegistrationResult(
        transform=best.transform,
        confidence=float(confidence),
        accepted=bool(confidence >= config.acceptance_threshold),
        method=method,
        losses={
            "loss": float(best.loss),
            "mean_residual_scene": float(best.mean_residual_A),
            "mean_residual_library": float(best.mean_residual_B),
            "iterations": float(best.iterations),
            "inlier_fraction": float(best.inlier_fraction),
            "inlier_fraction_scene": float(best.inlier_fraction_scene),
            "inlier_fraction_library": float(best.inlier_fraction_library),
            "containment": float(inside[order[0]]),
            "seen_free": float(free[order[0]]),
        },
        timings=timings,
        hypotheses=reports,
        proposal=proposal,
        thresholds={
            "acceptance_threshold": config.acceptance_threshold,
            "inlier_threshold": getattr(config.refine, "inlier_threshold", float("nan")),
        },
        history=list(best.history),
        samples=(np.asarray(scene_samples.points), np.asarray(lib_samples.points)),
    )


def single_hypothesis(config: RegistrationConfig) -> RegistrationConfig:
    """Only the best initial hypothesis is refined (as in the paper)."""
    return dataclasses.replace(config, init=dataclasses.replace(config.init, top_k=1))


def adam_method(config: RegistrationConfig) -> RegistrationConfig:
    """Ours with the paper's optimiser: Adam instead of Levenberg-Marquardt, every other
    setting unchanged (``regnf-adam``)."""
    return dataclasses.replace(config, refine=dataclasses.replace(config.refine, optimizer="adam"))


def paper_method(config: RegistrationConfig) -> RegistrationConfig:
    """Reg-NF as published: one hypothesis, and the paper's refinement, i.e. none of our
    refinement changes (kernel scale starting at 1, no scene level-set offset, no convergence
    stop: the residual stop or all 200 Adam iterations). Sampling and initialisation stay ours, so
    that a comparison isolates the refinement."""
    refine = dataclasses.replace(config.refine, optimizer="adam", kernel_scale_init=1.0,
                                 level_set_offset=False, convergence_window=0, prune_after=0)
    return dataclasses.replace(single_hypothesis(config), refine=refine)
