"""Discovery: registered instances from a scene field and a library, with no boxes given.

1. :func:`~regnf.registration.candidates.find_candidates`: upright boxes around what stands in
   the room.
2. A short registration of every library object in every candidate's box: the scene is
   sampled once per candidate and each library object once; on a subset of those samples,
   each object's initial hypotheses (features, RANSAC and the upright starts, screened by
   their SDF evidence) are found and the best one scored, without any refinement step, by the
   confidence the full registration would report (SDF evidence times containment times one less
   the share in seen free space).
   Scale-free: the library need not share the scene's units.
3. The full registration (every sample, initialisation and refinement, exactly as
   :func:`~regnf.registration.pipeline.register` in the candidate's box) of the ``shortlist``
   best-scored objects (those after the best only within ``shortlist_gap`` of it; all of those
   when the best scores below ``shortlist_uncertain``) and any other
   scored within ``shortlist_margin`` of the best
   (:meth:`Ranking.shortlisted`); the candidate is the accepted object of highest confidence, or
   unmatched: none was accepted, or the two best accepted ones differ only where the views did
   not look (ambiguous, :func:`~regnf.registration.observed_difference.observed_difference`).
4. The chosen registration is refined once more, from its pose, in the registered object's
   box (:func:`object_box`).

Two candidates whose boxes overlap are examined first as one, their points' union
(:func:`examined`): a part the views observed poorly can split one object in two. When the
union is matched and its object explains both halves' surface, the halves are not examined on
their own; otherwise they are, and the union replaces them only when neither is matched.

The same library object may be chosen for several candidates.

A candidate whose examination fails on its input (too few samples in its box, a degenerate
cloud: :data:`~regnf.registration.step_failures.SKIPPED_ERRORS`) is skipped with its reason
(:attr:`Discovery.skipped`), and a shortlisted object whose full registration fails so is left
out of the choice with its reason (:attr:`Tried.error`); the other candidates go on.

Candidates are examined side by side in worker processes when the fields' checkpoints are given
(:class:`FieldFiles`, :attr:`DiscoveryConfig.workers`): each examination runs on one thread
wherever it runs, so the result is the same bits as examining them one after another here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from regnf.core.errors import RegnfError
from regnf.core.threads import one_thread, worker_count
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.candidates import (
    Candidate,
    CandidateConfig,
    Candidates,
    box_iou,
    candidate_of,
    find_candidates,
)
from regnf.registration.initialisation import Hypothesis, InitConfig
from regnf.registration.observed_difference import UNOBSERVED, observed_difference
from regnf.registration.pipeline import (
    RegistrationConfig,
    check_fields,
    initialise,
    refine_hypotheses,
    register,
    sample_tensors,
    scored,
)
from regnf.registration.refinement import refine_many, without_steps
from regnf.registration.result import RegistrationResult
from regnf.registration.sampling import SurfaceSamples, sample_surface
from regnf.registration.step_failures import StepFailed, attempt
from regnf.render.evaluation import world_to_field


def _ranking_init() -> InitConfig:
    return dataclasses.replace(InitConfig(), ransac_runs=1, candidates=6)


@dataclass(frozen=True)
class DiscoveryConfig:
    """Settings of :func:`discover`."""

    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    """How candidates are found."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """How each shortlisted object is registered (its acceptance threshold decides)."""
    ranking_points: int = 1000
    """Samples (a seeded subset) of the scene and each library object to rank by (docs/decisions/discovery-ranking.md)."""
    ranking_init: InitConfig = field(default_factory=_ranking_init)
    """Initialisation of the short registration: 1 RANSAC run, 6 screened hypotheses (docs/decisions/discovery-ranking.md)."""
    shortlist: int = 2
    """Library objects fully registered per candidate, best-ranked first (docs/decisions/discovery-ranking.md)."""
    shortlist_gap: float = 0.15
    """Shortlisted objects score within this of the best (a confidence); inf: any (docs/decisions/discovery-ranking.md)."""
    shortlist_uncertain: float = 0.6
    """Best confidence under which all within ``shortlist_gap`` are registered; 0: never (docs/decisions/discovery-ranking.md)."""
    shortlist_margin: float = 0.05
    """Objects within this of the best score (a confidence) are registered too; 0: none (docs/decisions/discovery-ranking.md)."""

    unobserved_difference: float = UNOBSERVED
    """Observation of where two accepted objects differ under which neither is chosen (docs/decisions/discovery-ranking.md)."""
    difference_tolerance: float = 0.01
    """Surface farther than this fraction of the diagonal from the other object's is where two objects differ."""
    join_overlap: float = 0.02
    """Box IoU from which two candidates are first examined as one; 0 never joins (docs/decisions/discovery-ranking.md)."""
    half_explained: float = 0.5
    """A half is explained at this fraction of its points within ``explained_distance`` (docs/decisions/discovery-ranking.md)."""
    explained_distance: float = 0.03
    """Scene metres (the candidates' meshing cell, :attr:`CandidateConfig.resolution`)."""
    refit_box: bool = True
    """Refine the chosen registration again in its object's box, not the candidate's (docs/decisions/discovery-ranking.md)."""
    workers: int = 0
    """Candidate worker processes (given ``files``); 0: one per core, 1: none (docs/decisions/discovery-ranking.md)."""

    def __post_init__(self) -> None:
        if self.shortlist < 1:
            raise RegnfError(f"shortlist must be >= 1, got {self.shortlist}")
        if not (np.isfinite(self.shortlist_margin) and self.shortlist_margin >= 0):
            raise RegnfError(f"shortlist_margin must be finite and >= 0, got {self.shortlist_margin}")
        if not (np.isfinite(self.shortlist_uncertain) and 0 <= self.shortlist_uncertain <= 1):
            raise RegnfError(f"shortlist_uncertain must be in [0, 1], got {self.shortlist_uncertain}")
        if not self.shortlist_gap >= 0:
            raise RegnfError(f"shortlist_gap must be >= 0, got {self.shortlist_gap}")
        for name in ("join_overlap", "half_explained"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise RegnfError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not self.explained_distance > 0:
            raise RegnfError(f"explained_distance must be > 0, got {self.explained_distance}")
        if self.ranking_points < 50:
            raise RegnfError(f"ranking_points must be >= 50, got {self.ranking_points}")
        if self.workers < 0:
            raise RegnfError(f"workers must be >= 0, got {self.workers}")


class FieldFiles(NamedTuple):
    """The checkpoints the fields given to :func:`discover` were loaded from: worker processes
    load them again (a field is not sent from one process to another)."""

    scene: Path
    library: dict[str, Path]
    """Library object name -> checkpoint, for every object of the library."""


class Tried(NamedTuple):
    """One library object tried in a candidate's box."""

    library_name: str
    screened: float
    """Confidence of its best initial hypothesis before any refinement step (the shortlist's order)."""
    result: RegistrationResult | None
    """The full registration; None when the object was not shortlisted, or its registration failed."""
    error: str | None = None
    """Why its full registration failed on the input (``ExceptionType: message``); None when it did not."""


class Discovery(NamedTuple):
    """What became of one candidate."""

    candidate: Candidate
    """Its box and surface points, scene metres."""
    proposal: OrientedBox
    """The box in the scene field frame (what registration was given)."""
    tried: list[Tried]
    """Every library object, best screened first; the shortlisted ones fully registered (:meth:`Ranking.shortlisted`)."""
    chosen: Tried | None
    """The accepted registration of highest confidence, refit (:attr:`DiscoveryConfig.refit_box`); None: unmatched."""
    ambiguous: tuple[str, ...] = ()
    """Two accepted objects differing only where no view looked (:attr:`DiscoveryConfig.unobserved_difference`)."""
    skipped: str | None = None
    """Why the candidate was not examined (the step, ``ExceptionType: message``; then no ``tried`` or ``chosen``); None."""


class DiscoveryResult(NamedTuple):
    """Every candidate and what it became."""

    discoveries: list[Discovery]
    found: Candidates
    """The candidates with the support planes and surface points they came from."""
    seconds: dict
    """Time of ``candidates`` and ``registration``, and the ``total``."""

    @property
    def instances(self) -> list[Discovery]:
        """The candidates that were identified."""
        return [d for d in self.discoveries if d.chosen is not None]

    @property
    def unmatched(self) -> list[Discovery]:
        """The candidates examined and not identified."""
        return [d for d in self.discoveries if d.chosen is None and d.skipped is None]

    @property
    def skipped(self) -> list[Discovery]:
        """The candidates that could not be examined (:attr:`Discovery.skipped`)."""
        return [d for d in self.discoveries if d.skipped is not None]


def object_box(result: RegistrationResult) -> OrientedBox:
    """The registered object's box in the scene field frame: the bounds of its library
    samples, mapped by the inverse of the registration."""
    library_points = result.samples[1]
    box = OrientedBox.from_aabb(library_points.min(axis=0), library_points.max(axis=0))
    return box.transformed(result.transform.inverse().matrix())


def subset(samples: SurfaceSamples, n: int) -> SurfaceSamples:
    """At most ``n`` of ``samples`` (a seeded random subset, in their order)."""
    if len(samples.points) <= n:
        return samples
    keep = np.sort(np.random.default_rng(0).choice(len(samples.points), n, replace=False))
    return SurfaceSamples(samples.points[keep], samples.normals[keep], samples.view_ids[keep])


def screened_score(scene_field: Field, library_field: Field, proposal: OrientedBox,
                   scene: SurfaceSamples, library: SurfaceSamples, hypothesis: Hypothesis,
                   config: RegistrationConfig) -> float:
    """The confidence :func:`~regnf.registration.pipeline.register` would report for
    ``hypothesis`` with no refinement step: SDF evidence both ways, weighted by what the scene's
    views observed, times the library's containment in the proposal, times one less the share
    of its observed samples in seen free space."""
    A, B = sample_tensors(scene, library, library_field.device)
    at_start = refine_many(scene_field, library_field, A, B, [hypothesis.transform],
                           without_steps(config.refine))[0]
    return float(scored(at_start, library.points, proposal, config, scene_field)[0])


def discover(scene_field: Field, library: Mapping[str, Field],
             config: DiscoveryConfig | None = None, progress: bool = False,
             files: FieldFiles | None = None) -> DiscoveryResult:
    """Find, identify and register the library's objects in a scene field, with no boxes.

    Parameters
    ----------
    scene_field : Field
        A room (``to_world`` to metres, +Z up by default).
    library : mapping of name -> Field
        Library objects standing upright in their canonical frames; on the scene's device.
    config : DiscoveryConfig
    progress : bool
        Show a progress bar over the candidates.
    files : FieldFiles, optional
        The checkpoints ``scene_field`` and ``library`` were loaded from: candidates are then
        examined side by side in :attr:`DiscoveryConfig.workers` processes, with the same
        result. Without them, one after another in this process.

    Returns
    -------
    DiscoveryResult
        One :class:`Discovery` per candidate, largest first; a candidate whose examination
        failed on its input is there with its reason (:attr:`Discovery.skipped`).

    Raises
    ------
    ValueError
        No library object, ``files`` that do not name every library object, or a checkpoint
        that changed since discovery began (in a worker).
    RuntimeError
        An examination failed in a worker otherwise (a bug, or a worker that died).
    """
    cfg = config or DiscoveryConfig()
    reg = cfg.registration
    if not library:
        raise RegnfError("discovery needs at least one library object")
    if files is not None and set(files.library) != set(library):
        raise RegnfError(f"files name the library objects {sorted(files.library)}, the library holds "
                         f"{sorted(library)}")
    for f in library.values():
        check_fields(scene_field, f)

    def examine_all(cands: list[Candidate], on_done: Callable[[], None]) -> list[Discovery]:
        if pool is None or len(cands) < 2:
            out = []
            for cand in cands:
                out.append(examine(cand, scene_field, library, lib_samples, cfg))
                on_done()
            return out
        return pool.examine(cands, lib_samples, on_done)

    def explains(d: Discovery, half: Candidate) -> bool:
        assert d.chosen is not None and d.chosen.result is not None
        return explained_fraction(scene_field, library[d.chosen.library_name], d.chosen.result, half.points,
                                  cfg.explained_distance) >= cfg.half_explained

    workers = 1 if files is None else worker_count(cfg.workers or None)
    with contextlib.ExitStack() as stack:
        pool = None
        if files is not None and workers > 1:  # first: the workers load the fields while candidates are found
            from regnf.registration.discovery_workers import DiscoveryWorkers

            pool = stack.enter_context(DiscoveryWorkers(files, str(scene_field.device), cfg, workers))
        t0 = time.perf_counter()
        # One thread, as in register: the same surface, hypotheses and identities on any machine.
        with one_thread():
            found = find_candidates(scene_field, cfg.candidates)
        t1 = time.perf_counter()
        if pool is not None:
            lib_samples = pool.library_samples()
        else:
            with one_thread():
                lib_samples = {name: sample_surface(f, None, reg.library_sampling, side="library")
                               for name, f in library.items()}
        discoveries = examined(found, examine_all, explains, scene_field, cfg, progress)
    t2 = time.perf_counter()
    return DiscoveryResult(discoveries, found,
                           {"candidates": t1 - t0, "registration": t2 - t1, "total": t2 - t0})


class Ranking(NamedTuple):
    """The short registration of every library object in one candidate's box (step 2)."""

    proposal: OrientedBox
    """The candidate's box in the scene field frame."""
    scene_samples: SurfaceSamples
    """The scene sampled in the box (every full registration of the candidate reuses them)."""
    screened: dict[str, float]
    """Library object name -> the confidence of its best initial hypothesis."""
    sampling_seconds: float

    def order(self) -> list[str]:
        """The library, best screened first (ties by name)."""
        return sorted(self.screened, key=lambda n: (-round(self.screened[n], 6), n))

    def shortlisted(self, config: DiscoveryConfig) -> list[str]:
        """The objects to register fully: the best; the next best up to ``config.shortlist``
        (every one, when the best scores below ``config.shortlist_uncertain``) that score
        within ``config.shortlist_gap`` of it; and every other one within
        ``config.shortlist_margin`` of it (in :meth:`order`)."""
        order = self.order()
        best = round(self.screened[order[0]], 6)
        count = len(order) if best < config.shortlist_uncertain else config.shortlist
        return [n for i, n in enumerate(order)
                if i == 0 or (i < count and round(self.screened[n], 6) >= best - config.shortlist_gap)
                or round(self.screened[n], 6) >= best - config.shortlist_margin]


def proposal_of(cand: Candidate, scene_field: Field) -> OrientedBox:
    """The candidate's box in the scene field frame (what registration is given)."""
    return cand.box.transformed(np.linalg.inv(scene_field.to_world.detach().cpu().double().numpy()))


def rank_library(cand: Candidate, scene_field: Field, library: Mapping[str, Field],
                 library_samples: Mapping[str, SurfaceSamples], config: DiscoveryConfig) -> Ranking:
    """Step 2 for one candidate: sample its box, score every library object's best initial
    hypothesis there on a subset of the samples (:attr:`DiscoveryConfig.ranking_points`)."""
    reg = config.registration
    proposal = proposal_of(cand, scene_field)
    ts = time.perf_counter()
    with one_thread():
        scene_samples = sample_surface(scene_field, proposal, reg.scene_sampling, side="scene")
        sampling = time.perf_counter() - ts
        quick = dataclasses.replace(reg, init=config.ranking_init)
        few = subset(scene_samples, config.ranking_points)
        screened: dict[str, float] = {}
        for name, f in library.items():  # one short registration per library object
            lib_few = subset(library_samples[name], config.ranking_points)
            starts = initialise(scene_field, f, proposal, few, lib_few, quick)
            screened[name] = screened_score(scene_field, f, proposal, few, lib_few, starts[0], quick)
    return Ranking(proposal, scene_samples, screened, sampling)


def register_shortlisted(ranking: Ranking, scene_field: Field, library_field: Field,
                         library_samples: SurfaceSamples, config: DiscoveryConfig) -> RegistrationResult:
    """Step 3 for one shortlisted object: the full registration in the candidate's box, on the
    samples the ranking took, every initial hypothesis refined."""
    reg = config.registration
    # Every start refined: the identity compares two objects' confidences (the armchairs with
    # and without the pillow differ by 0.02-0.03), so each must be its best hypothesis's, not
    # the first one's (RegistrationConfig.confident_score).
    every_start = dataclasses.replace(reg, confident_score=math.inf)
    ti = time.perf_counter()
    with one_thread():
        starts = initialise(scene_field, library_field, ranking.proposal, ranking.scene_samples, library_samples, reg)
    return refine_hypotheses(scene_field, library_field, ranking.proposal, ranking.scene_samples, library_samples,
                             starts, every_start, timings={"sampling": ranking.sampling_seconds,
                                                           "initialisation": time.perf_counter() - ti})


def choose(cand: Candidate, ranking: Ranking, results: Mapping[str, RegistrationResult | StepFailed],
           scene_field: Field, library: Mapping[str, Field], library_samples: Mapping[str, SurfaceSamples],
           config: DiscoveryConfig) -> Discovery:
    """Step 4: the accepted registration of highest confidence among the shortlisted objects'
    ``results`` (unless ambiguous), refined once more in the registered object's box. A failed
    registration (:class:`StepFailed`) is kept as its object's :attr:`Tried.error`."""
    tried = []
    for name in ranking.order():
        r = results.get(name)
        failed = isinstance(r, StepFailed)
        tried.append(Tried(name, ranking.screened[name], None if failed else r, r.reason if failed else None))
    accepted = sorted((t for t in tried if t.result is not None and t.result.accepted),
                      key=lambda t: -t.result.confidence)
    chosen = accepted[0] if accepted else None
    ambiguous: tuple[str, ...] = ()
    if len(accepted) > 1:
        a, b = accepted[0], accepted[1]
        with one_thread():
            seen = observed_difference(scene_field, library[a.library_name], a.result, library[b.library_name],
                                       b.result, config.difference_tolerance)
        if seen < config.unobserved_difference:
            chosen, ambiguous = None, (a.library_name, b.library_name)
    if chosen is not None and config.refit_box:
        refit = register(scene_field, library[chosen.library_name], object_box(chosen.result), config.registration,
                         initial=chosen.result.transform, library_samples=library_samples[chosen.library_name])
        if refit.accepted:
            chosen = chosen._replace(result=refit)
    return Discovery(cand, ranking.proposal, tried, chosen, ambiguous)


def examine(cand: Candidate, scene_field: Field, library: Mapping[str, Field],
            library_samples: Mapping[str, SurfaceSamples], config: DiscoveryConfig) -> Discovery:
    """Steps 2-4 of the module docstring for one candidate, here and in order (the side-by-side
    path, :mod:`regnf.registration.discovery_workers`, runs the same steps in workers). A step
    that fails on its input skips the candidate, or leaves out one shortlisted object, with the
    reason recorded (:mod:`regnf.registration.step_failures`).

    Parameters
    ----------
    cand : Candidate
    scene_field : Field
    library : mapping of name -> Field
    library_samples : mapping of name -> SurfaceSamples
        Each library object's samples, taken with ``config.registration.library_sampling``.
    config : DiscoveryConfig
    """
    ranking = rank_or_skip(cand, scene_field, library, library_samples, config)
    if isinstance(ranking, Discovery):
        return ranking
    results = {name: attempt(register_shortlisted, ranking, scene_field, library[name], library_samples[name],
                             config)
               for name in ranking.shortlisted(config)}
    return choose_or_skip(cand, ranking, results, scene_field, library, library_samples, config)


def skipped_discovery(cand: Candidate, scene_field: Field, step: str, failed: StepFailed) -> Discovery:
    """The candidate skipped because ``step`` failed on its input."""
    return Discovery(cand, proposal_of(cand, scene_field), [], None, (), f"{step}: {failed.reason}")


def rank_or_skip(cand: Candidate, scene_field: Field, library: Mapping[str, Field],
                 library_samples: Mapping[str, SurfaceSamples], config: DiscoveryConfig) -> Ranking | Discovery:
    """:func:`rank_library`, or the candidate skipped when that fails on its input."""
    ranking = attempt(rank_library, cand, scene_field, library, library_samples, config)
    if isinstance(ranking, StepFailed):
        return skipped_discovery(cand, scene_field, "ranking the library in its box", ranking)
    return ranking


def choose_or_skip(cand: Candidate, ranking: Ranking, results: Mapping[str, RegistrationResult | StepFailed],
                   scene_field: Field, library: Mapping[str, Field], library_samples: Mapping[str, SurfaceSamples],
                   config: DiscoveryConfig) -> Discovery:
    """:func:`choose`, or the candidate skipped when that fails on its input."""
    chosen = attempt(choose, cand, ranking, results, scene_field, library, library_samples, config)
    if isinstance(chosen, StepFailed):
        return skipped_discovery(cand, scene_field, "choosing and refitting its object", chosen)
    return chosen


def overlapping_pairs(candidates: list[Candidate], min_iou: float) -> list[tuple[int, int]]:
    """Disjoint pairs ``(i, j)``, ``i < j``, of candidates whose boxes overlap by at least
    ``min_iou`` (:func:`box_iou`), most overlapping first; none when ``min_iou`` is 0."""
    if min_iou <= 0:
        return []
    overlaps = []
    for i, a in enumerate(candidates):  # a handful of candidates per room
        for j in range(i + 1, len(candidates)):
            b = candidates[j]
            reach = np.linalg.norm(a.box.half_extents) + np.linalg.norm(b.box.half_extents)
            if np.linalg.norm(a.box.center - b.box.center) < reach:  # else the boxes cannot meet
                iou = box_iou(a.box, b.box)
                if iou >= min_iou:
                    overlaps.append((-iou, i, j))
    used: set[int] = set()
    pairs = []
    for _, i, j in sorted(overlaps):
        if i not in used and j not in used:
            used |= {i, j}
            pairs.append((i, j))
    return pairs


def explained_fraction(scene_field: Field, library_field: Field, result: RegistrationResult,
                       points: np.ndarray, distance: float) -> float:
    """The fraction of ``points`` (n, 3, scene metres) within ``distance`` metres of the
    registered library object's surface (its SDF at the points mapped into its frame)."""
    local = world_to_field(scene_field, np.asarray(points, dtype=np.float64)).double().cpu().numpy()
    x = torch.as_tensor(result.transform.apply(local), dtype=torch.float32, device=library_field.device)
    with torch.no_grad():
        d = library_field.sdf(x).abs().double().cpu().numpy().reshape(-1)
    metres = d / result.transform.s * scene_field.world_scale
    return float(np.mean(metres <= distance)) if len(metres) else 0.0


def examined(found: Candidates,
             examine_all: Callable[[list[Candidate], Callable[[], None]], list[Discovery]],
             explains: Callable[[Discovery, Candidate], bool], scene_field: Field, config: DiscoveryConfig,
             progress: bool = False) -> list[Discovery]:
    """What ``examine_all`` makes of every candidate, overlapping ones first as one; largest box
    first.

    Each pair of :func:`overlapping_pairs` is examined as its points' union first. A matched
    union whose object ``explains`` both halves replaces them and they are not examined; else
    each half is examined, and a matched union replaces the pair only when neither half is
    matched nor ambiguous (see :attr:`DiscoveryConfig.join_overlap`).

    ``examine_all(candidates, on_done)`` examines a list of candidates (side by side, or one
    after another), calls ``on_done()`` after each and returns their discoveries in order. It
    is called twice: the unions and the candidates in no pair, then the halves not spared.
    """
    cands = found.candidates
    pairs = overlapping_pairs(cands, config.join_overlap)
    bar = tqdm(total=len(cands) + len(pairs), desc="discover: candidates", unit="candidate", disable=not progress)
    paired = {k for p in pairs for k in p}
    alone = [k for k in range(len(cands)) if k not in paired]
    union_cands = [candidate_of(np.concatenate([cands[i].points, cands[j].points]), found.supports, scene_field,
                                config.candidates) for i, j in pairs]
    first = examine_all(union_cands + [cands[k] for k in alone], bar.update)
    unions = dict(zip(pairs, first[:len(pairs)]))
    single: dict[int, Discovery] = dict(zip(alone, first[len(pairs):]))
    whole = [p for p, d in unions.items() if d.chosen is not None and all(explains(d, cands[k]) for k in p)]
    spared = {k for p in whole for k in p}
    bar.update(len(spared))
    halves = [k for p in pairs for k in p if k not in spared]
    single.update(zip(halves, examine_all([cands[k] for k in halves], bar.update)))
    single = {k: single[k] for k in sorted(single)}
    bar.close()
    out = [unions[p] for p in whole]
    for p, d in unions.items():
        if p not in whole and d.chosen is not None and all(
                single[k].chosen is None and not single[k].ambiguous for k in p):
            out.append(d)
            for k in p:
                del single[k]
    out += single.values()
    return sorted(out, key=lambda d: -float(np.prod(d.candidate.box.half_extents)))
