"""Bidirectional SDF refinement of a scene -> library similarity (docs/design.md section 1.5).

Given surface samples ``A`` of the object in the scene field (scene field frame) and ``B`` of
the library object (library field frame), and an initial similarity ``T0``, the refinement
minimises

    mean_{x in A} k(|S_lib(T x) - s S_scene(x)|) + mean_{y in B} k(|s S_scene(T^-1 y) - S_lib(y)|)
        + w L_reg

over ``T(x) = s R x + t`` and the kernel's (alpha, c), where ``k`` is Barron's adaptive robust
NLL (:mod:`regnf.registration.robust_loss`, one (alpha, c) pair shared by both terms) and ``L_reg`` the
trimmed mean of the squared distances from every mapped SCENE sample ``T x`` to its nearest
LIBRARY sample (pulling the library to the scene would punish library surface the scene never
saw). Both residuals are library distances: an SDF scales with its geometry, so the scene's is
multiplied by ``s``.

Units. The paper's thresholds are absolute numbers for fields normalised to [-1, 1]^3. Here
every length in the loss and every threshold is measured in the library's *reference length*
``L = max(bounds extent) / 2`` of the library field (1 for a field normalised to [-1, 1]^3, so
the paper's numbers carry over unchanged, and a library field kept in metres behaves the same).
The kernel sees residuals divided by ``L`` (so its scale init 1 means what it means in the
paper), the translation is learnt in units of ``L`` (so its learning rate does too), and scene-
side tolerances are the library ones mapped through the current scale (``s |S_scene| <= tol L``).

Parameterisation: ``R = exp([w]x) R0``, ``s = exp(l) s0`` (w, l start at 0), and a free
translation. The rotation and the scale are applied about ``c``, the centroid of ``T0(A)``
(``T(x) = e^l exp([w]x) (T0(x) - c) + c + L tau``, i.e. ``t = e^l exp([w]x)(t0 - c) + c + L tau``
with tau free, starting at 0): the same 7 degrees of freedom as ``(w, l, t)``, but a rotation
step no longer swings the object about the library origin, which would couple rotation and
translation (library objects have their origin at the base, not the centre).

Regulariser weight: the default 0.1 keeps the paper's term at no measurable cost in accuracy;
the SDF terms decide the basin, and a larger weight lets the nearest-neighbour distances, which
do not vanish at the truth, bias the optimum (docs/decisions/registration-refinement.md).

Two optimisers (``RefineConfig.optimizer``):

- ``lm`` (default, not in the paper): Levenberg-Marquardt. The objective is a robust
  least-squares problem in 8 parameters (pose, scale, offset), so each iteration writes out the
  residuals' Jacobians from the fields' spatial gradients (:meth:`_Batch.linearise`), fits each
  hypothesis's kernel (alpha, c) to its residuals by minimising their NLL (what Adam does by
  gradient steps), and solves a damped 8 x 8 system whose curvature is the loss's own (clamped
  at 0 where a term is not convex; :mod:`regnf.registration.irls`). 5-15 iterations instead of 80-200
  Adam steps, to the same or a tighter optimum (``docs/benchmarks.md``).
- ``adam``: the paper's, as published: Adam on all parameters and the kernel together.

Several hypotheses are refined in one batch (:func:`refine_many`): their samples are stacked so
that each iteration costs two field queries in all. Adam is elementwise, so one Adam over the
stacked per-hypothesis parameters is exactly K independent optimisations; Levenberg-Marquardt
solves, accepts and fits a kernel per hypothesis, which is the same.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple, TypeVar

import numpy as np
import torch

from regnf.core.threads import map_one_thread_each, one_thread, worker_count
from regnf.neural_fields.field import Field
from regnf.registration.irls import (
    barron_curvature,
    barron_weight,
    damped_step,
    fit_kernel,
    segment_gram,
    segment_normal_equations,
)
from regnf.registration.metrics import ObjectSymmetry, same_pose, symmetric_angle
from regnf.registration.robust_loss import AdaptiveRobustLoss, general_rho, log_partition
from regnf.registration.transform import SimilarityTransform

T = TypeVar("T")
U = TypeVar("U")


@dataclass(frozen=True)
class RefineConfig:
    """Bidirectional refinement settings: the paper's values where we follow it; each departure
    (optimiser, kernel scale, offset, stops, visibility) says why (docs/design.md section 1.5).

    Lengths marked *L* are in units of the library reference length (see the module docstring):
    for a library field normalised to [-1, 1]^3 they are plain library field units.
    """

    max_iterations: int = 200
    """Most Adam steps (*paper*: 200). (Learning rates stay constant, as in the paper: a decay
    saves steps on some objects at the cost of accuracy;
    docs/decisions/registration-refinement.md.)"""
    lr_rotation: float = 0.02
    """Adam learning rate of the axis-angle rotation update, radians (*paper*: 0.02)."""
    lr_translation: float = 0.01
    """Adam learning rate of the translation, *L* (*paper*: 0.01)."""
    lr_scale: float = 0.01
    """Adam learning rate of the log scale (*paper*: 0.01)."""
    lr_kernel: float = 0.005
    """Adam learning rate of the kernel's latent shape and scale (*paper*: 0.005)."""
    alpha_lo: float = 1e-6
    """Lower end of the kernel shape range (*paper*: alpha in (0, 1]; nerf2nerf's 1e-6)."""
    alpha_hi: float = 1.0
    """Upper end of the kernel shape range (*paper*: 1)."""
    kernel_scale_init: float = 0.01
    """Initial kernel scale c, *L* (*paper*: 1, but c moves slowly at ``lr_kernel`` and after
    200 steps is still about 0.5, far above residuals of 0.005: the kernel stays quadratic and
    robust to nothing. 0.01 is the surface tolerance: the scale of an inlier residual)."""
    resample_every: int = 10
    """Draw new samples every this many iterations (*paper*: 10); 0 never resamples."""
    jitter_fraction: float = 1.0 / 20.0
    """Jitter rho as a fraction of the scene radius (radius of the bounding sphere of A) (*paper*: 1/20)."""
    surface_tolerance: float = 0.01
    """A jittered sample is on a surface if |SDF| <= this, *L*, in each field (*paper* omega_1: 0.01)."""
    residual_tolerance: float = 0.02
    """...and its residual is <= this, *L* (*paper* omega_2: 0.02)."""
    min_spacing: float = 0.02
    """New samples are at least one voxel of this size, *L*, from existing ones (*paper* xi: 0.02)."""
    max_samples: int = 5000
    """Resampling stops growing a sample set at this size (*paper*: 5000)."""
    early_stop_residual: float = 0.0005
    """Stop when the mean residual of A is below this, *L* (*paper* text: 0.0005; its code: 0.001)."""
    regulariser_weight: float = 0.1
    """Weight w of the trimmed scene -> library nearest-neighbour term (module docstring;
    docs/decisions/registration-refinement.md)."""
    trim_fraction: float = 0.8
    """The regulariser averages this fraction of the smallest squared distances."""
    inlier_threshold: float = 0.01
    """Residuals <= this, *L*, count as inliers in the reported confidence (= surface_tolerance)."""
    bidirectional: bool = True
    """False: only the A term (no B term, no regulariser; B is ignored): the nerf2nerf-style baseline."""
    fix_scale: bool = False
    """True: the scale stays s0 (nerf2nerf assumes equal scales)."""
    seed: int = 0
    """Seed of the resampling jitter."""
    convergence_window: int = 20
    """Stop a hypothesis once its pose moved less than the three tolerances below over this many
    iterations; 0 disables. (Not in the paper, whose residual stop a neural scene field rarely
    reaches, so every hypothesis would run all 200 steps.)"""
    convergence_rotation: float = 1e-3
    """Rotation tolerance of that stop, radians."""
    convergence_translation: float = 1e-3
    """Tolerance on the motion of the mapped scene samples' centroid, *L*."""
    convergence_scale: float = 1e-3
    """Relative scale tolerance."""
    prune_after: int = 10
    """At this iteration stop refining every hypothesis whose inlier fraction trails the best one
    by more than ``prune_margin`` (it keeps its state and is reported); 0 disables."""
    prune_margin: float = 0.1
    """See ``prune_after``."""
    level_set_offset: bool = True
    """Learn a constant offset delta of the scene SDF: residuals use ``s S_scene + delta L``. (Not
    in the paper. A neural scene field is often dilated or eroded by a few mm; without delta the
    only way to absorb that is a wrong scale; docs/decisions/registration-refinement.md.)"""
    lr_offset: float = 0.003
    """Adam learning rate of delta, *L*."""
    max_offset: float = 0.01
    """Bound on |delta|, *L* (``delta = max_offset tanh(d)``; 0: unbounded). Delta is for a
    field dilated or eroded by a few mm; an object seen from one side leaves its depth along
    the view and delta free to trade against each other, and an unbounded delta takes that
    freedom (docs/decisions/registration-refinement.md)."""
    use_visibility: bool = True
    """Weight every residual (both terms, and the confidence) by how well the scene field's
    training views observed the place of its sample (``scene_field.visibility``, recorded at
    training; a field without it counts as observed everywhere). (Not in the paper. A field
    trained from a few views knows nothing of an object's far side: counting it as evidence
    rejects true poses and lets a 180-degree flip that fits the seen half win; a flip that puts
    library surface into observed free space is still charged for it.)"""
    visibility_lookahead: float = 3.0
    """A library sample (B) counts as observed as far as the space in front of its surface was:
    its weight is the visibility read this many grid voxels out along the library's outward
    normal, mapped into the scene at the current pose. 0 reads it at the sample itself.
    (Not in the paper. The grid counts space up to its margin, 2 voxels, behind an observed
    surface as observed, so the unseen underside of a thin top reads as observed at the
    sample. Scene samples (A) are read at the sample: read in front, the made-up surfaces
    bounding a field's fill, whose front is observed free space, would gain weight;
    docs/decisions/registration-refinement.md.)"""

    optimizer: Literal["lm", "adam"] = "lm"
    """``lm``: Levenberg-Marquardt, the kernel's (alpha, c) fitted to the residuals at every
    iterate (:mod:`regnf.registration.irls`); ``adam``: the paper's Adam on all parameters at once.
    (Not in the paper. The objective is a robust least-squares problem in 8 parameters: a
    damped Newton step converges in 5-15 iterations where Adam at the paper's rates takes
    80-200 steps; measured in ``docs/benchmarks.md``.)"""
    lm_max_iterations: int = 30
    """Most Levenberg-Marquardt iterations (``optimizer="lm"``); ``max_iterations`` caps Adam."""
    lm_resample_every: int = 3
    """Resample every this many LM iterations (Adam: ``resample_every``); 0 never resamples."""
    lm_resamples: int = 2
    """Resampling rounds at most (then the hypothesis converges on fixed samples): without a
    limit the samples keep changing and the stop is rarely reached; without rounds the
    confidence is lower (docs/decisions/registration-refinement.md)."""
    lm_prune_after: int = 6
    """At this LM iteration stop hypotheses whose inlier fraction trails the best one (running or
    already stopped: a best one that converged early still counts) by more than ``prune_margin``
    (Adam: ``prune_after``); 0 disables, merging too. A start that tilts before it settles can trail
    for the first few iterations (docs/decisions/registration-refinement.md)."""
    lm_merge_rotation_deg: float = 5.0
    """From iteration ``lm_prune_after`` on, a hypothesis that comes this close in rotation
    (degrees, modulo the object's symmetry), ``lm_merge_scale`` in scale and ``lm_merge_shift``
    in where it maps the scene samples' centroid to a hypothesis with a higher inlier fraction
    (running or stopped) stops: both are heading for one pose; 0 disables. (Not in the paper;
    docs/decisions/registration-refinement.md.)"""
    lm_merge_scale: float = 0.05
    """See ``lm_merge_rotation_deg``: relative scale."""
    lm_merge_shift: float = 0.1
    """See ``lm_merge_rotation_deg``: *L*."""
    lm_step_tolerance: float = 1e-4
    """A hypothesis has converged once an LM step would move it less than this in rotation
    (radians), in the mapped centroid of A (*L*), in relative scale and in the level-set
    offset (*L*)."""
    lm_curvature: Literal["irls", "newton"] = "newton"
    """Curvature of each robust term in the LM system: ``irls`` the reweighting's ``rho'(x)/x``
    (a majoriser: safe steps, but linear convergence); ``newton`` the loss's own
    ``max(rho''(x), 0)`` (a fraction of the iterations to the same pose), falling back to
    ``irls`` for the next step after a rejected one (docs/decisions/registration-refinement.md)."""
    lm_damping: float = 1e-3
    """Initial Levenberg-Marquardt damping mu (relative to the diagonal), then Nielsen's update
    from the gain ratio (the loss's decrease over the decrease the model predicted)."""

    def __post_init__(self) -> None:
        positive = ("lr_rotation", "lr_translation", "lr_scale", "lr_kernel", "kernel_scale_init",
                    "jitter_fraction", "surface_tolerance", "residual_tolerance", "min_spacing",
                    "inlier_threshold")
        for name in positive:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"RefineConfig.{name} must be finite and > 0, got {v}")
        if self.optimizer not in ("lm", "adam"):
            raise ValueError(f"RefineConfig.optimizer must be 'lm' or 'adam', got {self.optimizer!r}")
        if not (math.isfinite(self.lm_step_tolerance) and self.lm_step_tolerance > 0
                and math.isfinite(self.lm_damping) and self.lm_damping > 0):
            raise ValueError("RefineConfig.lm_step_tolerance and lm_damping must be finite and > 0")
        for name in ("max_iterations", "resample_every", "max_samples", "lm_max_iterations",
                     "lm_resample_every", "lm_resamples", "lm_prune_after"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"RefineConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.regulariser_weight) and self.regulariser_weight >= 0):
            raise ValueError(f"RefineConfig.regulariser_weight must be >= 0, got {self.regulariser_weight}")
        for name in ("lm_merge_rotation_deg", "lm_merge_scale", "lm_merge_shift"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"RefineConfig.{name} must be finite and >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.visibility_lookahead) and self.visibility_lookahead >= 0):
            raise ValueError(f"RefineConfig.visibility_lookahead must be >= 0, got {self.visibility_lookahead}")
        if not (math.isfinite(self.max_offset) and self.max_offset >= 0):
            raise ValueError(f"RefineConfig.max_offset must be >= 0, got {self.max_offset}")
        if not 0.0 < self.trim_fraction <= 1.0:
            raise ValueError(f"RefineConfig.trim_fraction must be in (0, 1], got {self.trim_fraction}")
        if not self.early_stop_residual >= 0:
            raise ValueError(f"RefineConfig.early_stop_residual must be >= 0, got {self.early_stop_residual}")
        if not 0.0 <= self.alpha_lo < self.alpha_hi <= 2.0:
            raise ValueError(f"need 0 <= alpha_lo < alpha_hi <= 2, got ({self.alpha_lo}, {self.alpha_hi})")


class RefineResult(NamedTuple):
    """The outcome of refining one hypothesis.

    Residuals are in library field units; ``inlier_fraction`` counts residuals of both sets
    (A only when not bidirectional) at most ``inlier_threshold`` reference lengths.
    """

    transform: SimilarityTransform
    """Scene field frame -> library field frame after the last step."""
    loss: float
    """Loss of ``transform`` (NLL terms + w * regulariser)."""
    mean_residual_A: float
    """Mean |S_lib(T x) - s S_scene(x)| over the final A, library units."""
    mean_residual_B: float
    """Mean |s S_scene(T^-1 y) - S_lib(y)| over the final B, library units (nan if unused)."""
    inlier_fraction: float
    """Fraction of residuals <= inlier_threshold * L: a confidence in [0, 1]."""
    iterations: int
    """Optimiser iterations taken (Adam steps or Levenberg-Marquardt iterations)."""
    history: list[dict]
    """Per iteration: loss, mean residuals, alpha, c, s, the level-set offset (*L*), sample counts."""
    seconds: float
    """Wall time of the whole batch this hypothesis was refined in."""
    inlier_fraction_scene: float = float("nan")
    """The inlier fraction of the scene samples' residuals alone (A -> library)."""
    inlier_fraction_library: float = float("nan")
    """The inlier fraction of the library samples' residuals alone (B -> scene; nan if unused)."""
    offset: float = 0.0
    """The level-set offset delta of ``transform``, *L* (0 without ``level_set_offset``)."""


def without_steps(config: RefineConfig) -> RefineConfig:
    """``config`` with no optimisation step: refining with it scores the initial poses."""
    return dataclasses.replace(config, max_iterations=0, lm_max_iterations=0)


def reference_length(library_field: Field) -> float:
    """The library's unit of length for thresholds: half the longest extent of its bounds."""
    ext = (library_field.bounds[1] - library_field.bounds[0]).detach().double().cpu()
    return 0.5 * float(ext.max())


# -- small helpers ---------------------------------------------------------------------------


@contextlib.contextmanager
def _frozen(*modules: torch.nn.Module) -> Iterator[None]:
    """No gradients to the fields' own parameters (autograd w.r.t. query points still flows)."""
    params = {id(p): p for m in modules for p in m.parameters()}
    saved = {k: p.requires_grad for k, p in params.items()}
    try:
        for p in params.values():
            p.requires_grad_(False)
        yield
    finally:
        for k, p in params.items():
            p.requires_grad_(saved[k])


def _skew(w: torch.Tensor) -> torch.Tensor:
    """(k, 3) axis-angle -> (k, 3, 3) cross-product matrices."""
    z = torch.zeros_like(w[:, 0])
    return torch.stack([
        torch.stack([z, -w[:, 2], w[:, 1]], dim=-1),
        torch.stack([w[:, 2], z, -w[:, 0]], dim=-1),
        torch.stack([-w[:, 1], w[:, 0], z], dim=-1),
    ], dim=-2)


def _check_points(x: torch.Tensor | None, what: str, device: torch.device) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != 3:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{what} must be a (n, 3) tensor, got {shape}")
    if x.shape[0] == 0:
        raise ValueError(f"{what} is empty: refinement needs surface samples")
    if not x.is_floating_point():
        raise ValueError(f"{what} must be a float tensor, got {x.dtype}")
    if x.device != device:
        raise ValueError(f"{what} is on {x.device} but the fields are on {device}; move them to one device")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{what} contains non-finite coordinates")
    return x


def _check_transform(T: SimilarityTransform, k: int) -> None:
    R = np.asarray(T.R, dtype=np.float64)
    t = np.asarray(T.t, dtype=np.float64).reshape(-1)
    s = float(T.s)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"initial transform {k}: R must be 3x3 and t have 3 entries")
    if not (np.isfinite(R).all() and np.isfinite(t).all() and math.isfinite(s) and s > 0):
        raise ValueError(f"initial transform {k} has non-finite entries or a scale <= 0 (s = {s})")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise ValueError(f"initial transform {k}: R is not a rotation")


def _check_finite(values: torch.Tensor, what: str) -> None:
    bad = ~torch.isfinite(values)
    if bool(bad.any()):
        raise ValueError(f"{what} returned non-finite SDF values at {int(bad.sum())} of "
                         f"{values.numel()} samples")


def _segment_mean(values: torch.Tensor, group: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """(k,) mean of ``values`` (n,) per group (n,) long, ``counts`` (k,) float."""
    out = values.new_zeros(counts.shape[0])
    return out.index_add(0, group, values) / counts.clamp(min=1)


def _split_rows(columns: list[torch.Tensor | None], tensors: list[torch.Tensor]) -> list[tuple]:
    """Per tensor of ``tensors`` (stacked in that order), its rows of each column (None: None)."""
    sizes = [t.shape[0] for t in tensors]
    return list(zip(*(c.split(sizes) if c is not None else [None] * len(sizes) for c in columns)))


def _segment_sum(values: torch.Tensor, group: torch.Tensor, k: int) -> torch.Tensor:
    """(k,) sum of ``values`` (n,) per group (n,) long."""
    return values.new_zeros(k).index_add(0, group, values)


class _Nearest:
    """Nearest-neighbour lookup into a fixed point set (KD-tree on CPU, brute force on GPU)."""

    CHUNK = 4096

    def __init__(self, points: torch.Tensor) -> None:
        # Double precision on both paths (the KD-tree's), whatever the points' dtype: the
        # queries come in float64 and the nearest point must not depend on the device.
        self.points = points.detach().double()
        self.tree = None
        if points.device.type == "cpu":
            from scipy.spatial import cKDTree

            self.tree = cKDTree(self.points.numpy())

    def query(self, x: torch.Tensor) -> torch.Tensor:
        """(n,) long index of the nearest point to each query (n, 3); no gradient."""
        x = x.detach()
        if self.tree is not None:
            _, idx = self.tree.query(x.double().numpy(), k=1)
            return torch.as_tensor(idx, dtype=torch.long)
        x = x.double()
        parts = [torch.cdist(x[i:i + self.CHUNK], self.points).argmin(dim=1)
                 for i in range(0, x.shape[0], self.CHUNK)]
        return torch.cat(parts)


def _voxel_new(existing: torch.Tensor, candidates: torch.Tensor, voxel: float) -> torch.Tensor:
    """(m,) bool: candidates (m, 3) in voxels free of ``existing`` (n, 3), first one per voxel."""
    m = candidates.shape[0]
    if m == 0:
        return torch.zeros(0, dtype=torch.bool, device=candidates.device)
    keys = torch.floor(torch.cat([existing, candidates]) / voxel).long()
    _, inv = torch.unique(keys, dim=0, return_inverse=True)
    n_vox = int(inv.max()) + 1
    taken = torch.zeros(n_vox, dtype=torch.bool, device=keys.device)
    taken[inv[: existing.shape[0]]] = True
    cinv = inv[existing.shape[0]:]
    order = torch.arange(m, device=keys.device)
    first = torch.full((n_vox,), m, dtype=torch.long, device=keys.device)
    first.scatter_reduce_(0, cinv, order, reduce="amin")
    return (~taken[cinv]) & (first[cinv] == order)


def _unit_directions(n: int, gen: torch.Generator, like: torch.Tensor) -> torch.Tensor:
    """(n, 3) uniformly random unit vectors (drawn on the CPU: reproducible on any device)."""
    u = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True).clamp(min=1e-12)
    return u.to(device=like.device, dtype=like.dtype)


def _bounding_radius(x: torch.Tensor) -> float:
    """Radius of the bounding sphere about the AABB centre of points (n, 3)."""
    centre = 0.5 * (x.min(dim=0).values + x.max(dim=0).values)
    return float((x - centre).norm(dim=1).max())


# -- the batched problem ---------------------------------------------------------------------


class _Linear(NamedTuple):
    """The active hypotheses' residuals at their current pose and the residuals' Jacobians in
    the local update ``(dw, dl, dtau, d delta)`` (rotation, log scale, translation, offset).

    Rows of the SDF terms are grouped by hypothesis (``group``, active index); residuals are
    in reference lengths, signed."""

    x: torch.Tensor
    """(n,) float64 SDF residuals (A rows, then B rows)."""
    J: torch.Tensor
    """(n, 8) float64 d x / d (dw, dl, dtau, d delta)."""
    a: torch.Tensor
    """(n,) float64 weight of each residual in its hypothesis's objective (the visibility over
    the weighted count of its set: each set contributes a weighted mean)."""
    group: torch.Tensor
    """(n,) long."""
    q: torch.Tensor
    """(m, 3) float64 regulariser vectors: kept mapped scene samples minus their nearest library
    sample, reference lengths."""
    Jq: torch.Tensor
    """(m, 3, 8) float64 their Jacobians."""
    aq: torch.Tensor
    """(m,) float64 regulariser weight of each vector (w over the kept count)."""
    gq: torch.Tensor
    """(m,) long hypothesis of each vector."""
    stats: torch.Tensor
    """(k, 7) as :meth:`_Batch.evaluate`."""

    def merge(self, other: _Linear, take: torch.Tensor) -> _Linear:
        """Rows of ``other`` for the hypotheses where ``take`` (k,) is true, else these rows (the
        two must share their sample sets)."""
        rows, reg = take[self.group], take[self.gq]
        return _Linear(
            torch.where(rows, other.x, self.x), torch.where(rows[:, None], other.J, self.J),
            torch.where(rows, other.a, self.a), self.group,
            torch.where(reg[:, None], other.q, self.q), torch.where(reg[:, None, None], other.Jq, self.Jq),
            torch.where(reg, other.aq, self.aq), self.gq, torch.where(take[:, None], other.stats, self.stats))

    def select(self, keep: torch.Tensor) -> _Linear:
        """Only the hypotheses where ``keep`` (k,) is true, renumbered in order."""
        new_id = torch.cumsum(keep.long(), 0) - 1
        rows, reg = keep[self.group], keep[self.gq]
        return _Linear(self.x[rows], self.J[rows], self.a[rows], new_id[self.group[rows]], self.q[reg],
                       self.Jq[reg], self.aq[reg], new_id[self.gq[reg]], self.stats[keep])


class _Batch:
    """K hypotheses' parameters, samples and cached SDFs, refined together."""

    def __init__(
        self,
        scene: Field,
        library: Field,
        A: torch.Tensor,
        B: torch.Tensor | None,
        inits: Sequence[SimilarityTransform],
        cfg: RefineConfig,
        workers: int = 1,
    ) -> None:
        self.scene, self.library, self.cfg = scene, library, cfg
        self.workers = workers
        # Where the scene's training views observed space (None: everywhere, e.g. analytic or
        # mesh-distilled scenes). Samples in unobserved space are no evidence either way.
        self.visibility = getattr(scene, "visibility", None) if cfg.use_visibility else None
        # The lookahead in scene units (grid voxels: their longest edge).
        self.lookahead = (cfg.visibility_lookahead * float(self.visibility.voxel_size.max())
                          if self.visibility is not None else 0.0)
        self.normal_B: torch.Tensor | None = None
        self.K = K = len(inits)
        dev, dt = A.device, A.dtype
        self.dtype = dt
        self.L = reference_length(library)
        self.rho = cfg.jitter_fraction * _bounding_radius(A)  # scene units
        f64 = {"device": dev, "dtype": torch.float64}
        self.R0 = torch.stack([torch.as_tensor(np.asarray(T.R), **f64) for T in inits])
        self.t0 = torch.stack([torch.as_tensor(np.asarray(T.t).reshape(3), **f64) for T in inits])
        self.s0 = torch.tensor([float(T.s) for T in inits], **f64)
        # Centre of rotation and scaling: the centroid of T0(A) in the library frame.
        a_mean = A.double().mean(dim=0)
        self.a_mean = a_mean
        self.centre = self.s0[:, None] * (self.R0 @ a_mean) + self.t0
        self.w = torch.zeros(K, 3, requires_grad=True, **f64)
        self.log_s = torch.zeros(K, requires_grad=not cfg.fix_scale, **f64)
        self.tau = torch.zeros(K, 3, requires_grad=True, **f64)
        self.delta = torch.zeros(K, requires_grad=cfg.level_set_offset, **f64)
        self.kernel = AdaptiveRobustLoss(
            K, alpha_lo=cfg.alpha_lo, alpha_hi=cfg.alpha_hi, scale_init=cfg.kernel_scale_init
        ).to(dev)
        # One generator per hypothesis, all with the same seed: a hypothesis draws the same
        # jitter whether it is refined alone or in a batch.
        self.gens = [torch.Generator().manual_seed(int(cfg.seed)) for _ in range(K)]
        self.bidirectional = cfg.bidirectional
        # One tensor shared by every hypothesis until its resampling replaces it: what does not
        # move with the pose is computed once per distinct tensor (see _fixed_values).
        self.A = [A.detach()] * K
        self.B = [B.detach()] * K if self.bidirectional else []
        self.fixed_A: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = {}
        self.fixed_B: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, _Nearest | None]] = {}
        self.active = list(range(K))
        self.stopped: dict[int, dict[str, torch.Tensor]] = {}
        self._rebuild()

    # -- pose -------------------------------------------------------------------------------
    def pose(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(K, 3, 3) R, (K, 3) t, (K,) s in float64, differentiable in the parameters."""
        E = torch.linalg.matrix_exp(_skew(self.w))
        e = torch.exp(self.log_s)
        R = E @ self.R0
        s = e * self.s0
        t = e[:, None] * (E @ (self.t0 - self.centre)[..., None])[..., 0] + self.centre + self.L * self.tau
        return R, t, s

    def offset(self) -> torch.Tensor:
        """(K,) level-set offset delta, *L*, bounded by ``max_offset``."""
        m = self.cfg.max_offset
        return m * torch.tanh(self.delta / m) if m > 0 else self.delta

    # -- samples ----------------------------------------------------------------------------
    def _rebuild(self) -> None:
        """Stack the active hypotheses' samples and the SDFs that do not move with the pose."""
        act = self.active
        dev = self.A[0].device
        self._fixed_values()
        self.gA = torch.cat([torch.full((self.A[k].shape[0],), i, dtype=torch.long, device=dev)
                             for i, k in enumerate(act)])
        self.xA = torch.cat([self.A[k] for k in act])
        self.nA = torch.tensor([float(self.A[k].shape[0]) for k in act], device=dev)
        self.sA = torch.cat([self.fixed_A[k][1] for k in act])  # S_scene(A): fixed in the scene frame
        self.wA = None if self.visibility is None else torch.cat([self.fixed_A[k][2] for k in act])
        if self.bidirectional:
            self.gB = torch.cat([torch.full((self.B[k].shape[0],), i, dtype=torch.long, device=dev)
                                 for i, k in enumerate(act)])
            self.yB = torch.cat([self.B[k] for k in act])
            self.nB = torch.tensor([float(self.B[k].shape[0]) for k in act], device=dev)
            self.sB = torch.cat([self.fixed_B[k][1] for k in act])  # S_lib(B): fixed in the library frame
            # Outward library normals at B, for the visibility lookup in front of them.
            self.normal_B = torch.cat([self.fixed_B[k][2] for k in act]) if self.lookahead > 0 else None
            self.nearest = [self.fixed_B[k][3] for k in act] if self.cfg.regulariser_weight > 0 else []

    def _both(self, scene_side: Callable[[], T], library_side: Callable[[], U]) -> tuple[T, U]:
        """``(scene_side(), library_side())``: the two directions' field queries are independent,
        so with ``workers`` > 1 they run side by side, each on one CPU thread
        (:func:`~regnf.core.threads.map_one_thread_each`): the bits of one after the other.

        Not under autograd (Adam's loss): the backward pass orders its nodes by a creation
        counter that torch keeps per thread, so a graph built on two threads sums the pose's
        gradient contributions in an order that depends on the scheduling (seen: one run in six
        differed in the last bits)."""
        if self.workers < 2 or torch.is_grad_enabled():
            return scene_side(), library_side()
        a, b = map_one_thread_each(lambda call: call(), [scene_side, library_side], 2)
        return a, b

    def _fixed_values(self) -> None:
        """Evaluate, for the active hypotheses whose samples changed, what does not move with the
        pose: S_scene and the visibility at A; S_lib, the library normals and the nearest-sample
        lookup at B. Once per distinct sample tensor, in one field query per side (the fields
        are the cost: measured, re-evaluating them whenever a hypothesis stopped took a third of
        the refinement)."""
        if not self.bidirectional:
            self._cache_per_tensor(self.A, self.fixed_A, self._fixed_at_A)
            return
        self._both(lambda: self._cache_per_tensor(self.A, self.fixed_A, self._fixed_at_A),
                   lambda: self._cache_per_tensor(self.B, self.fixed_B, self._fixed_at_B))

    def _cache_per_tensor(self, sets: list[torch.Tensor], cache: dict,
                          evaluate: Callable[[list[torch.Tensor]], list[tuple]]) -> None:
        """``cache[k] = (sets[k], *values)`` for each active hypothesis whose sample tensor the
        cache does not hold yet; ``evaluate`` gets each such tensor once and returns its values."""
        todo = {id(sets[k]): sets[k] for k in self.active if cache.get(k, (None,))[0] is not sets[k]}
        if not todo:
            return
        values = dict(zip(todo, evaluate(list(todo.values()))))
        for k in self.active:
            if id(sets[k]) in values:
                cache[k] = (sets[k], *values[id(sets[k])])

    def _fixed_at_A(self, tensors: list[torch.Tensor]) -> list[tuple]:
        """Per scene sample tensor: S_scene and the visibility (None without) at its points."""
        x = torch.cat(tensors)
        with torch.no_grad():
            sdf = self.scene.sdf(x)
            w = self._observed(x)
        _check_finite(sdf, "the scene field (at A)")
        return _split_rows([sdf, w], tensors)

    def _fixed_at_B(self, tensors: list[torch.Tensor]) -> list[tuple]:
        """Per library sample tensor: S_lib, the outward normals (None without a lookahead) and
        the nearest-sample lookup (None without the regulariser)."""
        y = torch.cat(tensors)
        with torch.no_grad():
            sdf = self.library.sdf(y)
            normal = self.library.normal(y) if self.lookahead > 0 else None
        _check_finite(sdf, "the library field (at B)")
        return [(*row, _Nearest(t) if self.cfg.regulariser_weight > 0 else None)
                for row, t in zip(_split_rows([sdf, normal], tensors), tensors)]

    def resample(self) -> None:
        """Jitter every sample by rho; keep new ones on both surfaces, spaced apart, up to the cap."""
        cfg, L = self.cfg, self.L
        with torch.no_grad():
            R, t, s = (v.to(self.dtype) for v in self.pose())
            act = self.active
            idx = torch.tensor(act, device=R.device)
            R, t, s = R[idx], t[idx], s[idx]
            # Scene side: jitter A in the scene frame.
            cA = self.xA + self.rho * self._directions(self.A, self.xA)
            ssc = self.scene.sdf(cA)
            yc = s[self.gA, None] * torch.einsum("nij,nj->ni", R[self.gA], cA) + t[self.gA]
            slib = self.library.sdf(yc)
            res = (slib - s[self.gA] * ssc).abs()
            okA = ((s[self.gA] * ssc).abs() <= cfg.surface_tolerance * L) \
                & (slib.abs() <= cfg.surface_tolerance * L) & (res <= cfg.residual_tolerance * L)
            for i, k in enumerate(act):
                sel = okA & (self.gA == i)
                self.A[k] = self._grow(self.A[k], cA[sel], cfg.min_spacing * L / float(s[i]), k)
            if self.bidirectional:
                # Library side: jitter B in the library frame by the same physical distance.
                jit = (self.rho * s)[self.gB, None]
                cB = self.yB + jit * self._directions(self.B, self.yB)
                slib = self.library.sdf(cB)
                xc = torch.einsum("nji,nj->ni", R[self.gB], cB - t[self.gB]) / s[self.gB, None]
                ssc = s[self.gB] * self.scene.sdf(xc)
                okB = (slib.abs() <= cfg.surface_tolerance * L) & (ssc.abs() <= cfg.surface_tolerance * L) \
                    & ((ssc - slib).abs() <= cfg.residual_tolerance * L)
                for i, k in enumerate(act):
                    sel = okB & (self.gB == i)
                    self.B[k] = self._grow(self.B[k], cB[sel], cfg.min_spacing * L, k)
        self._rebuild()

    def _observed(self, x: torch.Tensor, normals: torch.Tensor | None = None) -> torch.Tensor | None:
        """(n,) observation weights in [0, 1] of surface samples ``x`` (n, 3, scene frame), read
        ``visibility_lookahead`` voxels out along their unit outward ``normals`` (n, 3, scene
        frame) where given; None: all observed."""
        if self.visibility is None:
            return None
        x = x.detach()
        if normals is not None:
            x = x + self.lookahead * normals.to(x.dtype)
        return self.visibility.observed(x).to(x.dtype)

    def _normals_B(self, R: torch.Tensor) -> torch.Tensor | None:
        """(n, 3) the library normals at B in the scene frame, by their hypotheses' rotations
        ``R`` (k, 3, 3, active ones); None without a lookahead."""
        if self.normal_B is None:
            return None
        return torch.einsum("nji,nj->ni", R[self.gB].to(self.normal_B.dtype), self.normal_B)

    def _directions(self, sets: list[torch.Tensor], like: torch.Tensor) -> torch.Tensor:
        """(n, 3) random unit jitter directions for the stacked active sets, per-hypothesis streams."""
        return torch.cat([_unit_directions(sets[k].shape[0], self.gens[k], like) for k in self.active])

    def _grow(self, existing: torch.Tensor, cand: torch.Tensor, voxel: float, k: int) -> torch.Tensor:
        """``existing`` plus the candidates in voxels it leaves free, capped at max_samples."""
        room = self.cfg.max_samples - existing.shape[0]
        if room <= 0 or cand.shape[0] == 0:
            return existing
        cand = cand[_voxel_new(existing, cand, voxel)]
        if cand.shape[0] > room:
            pick = torch.randperm(cand.shape[0], generator=self.gens[k])[:room].to(cand.device)
            cand = cand[pick]
        return torch.cat([existing, cand])

    # -- the objective ----------------------------------------------------------------------
    def evaluate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Loss per active hypothesis (k,) and a (k, 7) stats table (no grad): mean rA, mean rB,
        inlier count, residual count, regulariser, and the inlier count and residual count of A
        alone; residuals in library units, counts weighted by the visibility."""
        cfg, L = self.cfg, self.L
        R, t, s = self.pose()
        idx = torch.tensor(self.active, device=R.device)
        R, t, s = R[idx].to(self.dtype), t[idx].to(self.dtype), s[idx].to(self.dtype)
        gA = self.gA
        yA = s[gA, None] * torch.einsum("nij,nj->ni", R[gA], self.xA) + t[gA]
        d = (self.offset()[idx] * L).to(self.dtype)
        if self.bidirectional:
            gB = self.gB
            xB = torch.einsum("nji,nj->ni", R[gB], self.yB - t[gB]) / s[gB, None]
            scene_at_xB, lib_at_yA = self._both(lambda: self.scene.sdf(xB), lambda: self.library.sdf(yA))
        else:
            lib_at_yA = self.library.sdf(yA)
        rA = (lib_at_yA - s[gA] * self.sA - d[gA]).abs()
        k = len(self.active)
        if self.wA is None:
            loss = _segment_mean(self.kernel(rA / L, idx[gA]), gA, self.nA)
            meanA = _segment_mean(rA.detach(), gA, self.nA)
            inl = _segment_mean((rA.detach() <= cfg.inlier_threshold * L).to(rA.dtype), gA, self.nA) * self.nA
            count = self.nA.clone()
        else:  # every sum weighted by how well the scene's views observed the sample's place
            wA = self.wA.to(rA.dtype)
            count = _segment_sum(wA, gA, k)
            loss = _segment_mean(wA * self.kernel(rA / L, idx[gA]), gA, count)
            meanA = _segment_mean(wA * rA.detach(), gA, count)
            inl = _segment_sum(wA * (rA.detach() <= cfg.inlier_threshold * L).to(rA.dtype), gA, k)
        meanB = torch.full_like(meanA, float("nan"))
        reg = torch.zeros_like(meanA)
        inl_A, count_A = inl.detach().clone(), count.detach().clone()
        if self.bidirectional:
            rB = (s[gB] * scene_at_xB + d[gB] - self.sB).abs()
            # In front of where the library sample lands in the scene, at this pose.
            wB = self._observed(xB, self._normals_B(R))
            if wB is None:
                loss = loss + _segment_mean(self.kernel(rB / L, idx[gB]), gB, self.nB)
                meanB = _segment_mean(rB.detach(), gB, self.nB)
                inl = inl + _segment_mean((rB.detach() <= cfg.inlier_threshold * L).to(rB.dtype), gB,
                                          self.nB) * self.nB
                count = count + self.nB
            else:
                cB = _segment_sum(wB, gB, k)
                loss = loss + _segment_mean(wB * self.kernel(rB / L, idx[gB]), gB, cB)
                meanB = _segment_mean(wB * rB.detach(), gB, cB)
                inl = inl + _segment_sum(wB * (rB.detach() <= cfg.inlier_threshold * L).to(rB.dtype), gB, k)
                count = count + cB
            if cfg.regulariser_weight > 0:
                reg = torch.stack([self._regulariser(yA[gA == i], k) for i, k in enumerate(self.active)])
                loss = loss + cfg.regulariser_weight * reg
        stats = torch.stack([meanA, meanB, inl, count, reg.detach(), inl_A, count_A], dim=1)
        return loss, stats.detach()

    def _regulariser(self, yA: torch.Tensor, k: int) -> torch.Tensor:
        """Trimmed mean of squared distances (in L^2) from mapped scene samples to library samples."""
        B = self.B[k]
        nn = self.nearest[self.active.index(k)].query(yA).to(B.device)
        d2 = ((yA - B[nn]) ** 2).sum(dim=1) / self.L**2
        keep = max(1, math.floor(self.cfg.trim_fraction * d2.shape[0]))
        return torch.topk(d2, keep, largest=False, sorted=False).values.mean()

    # -- Levenberg-Marquardt -----------------------------------------------------------------
    def linearise(self) -> _Linear:
        """Residuals, Jacobians and stats of the active hypotheses at their pose (no autograd
        through the pose: the fields' spatial gradients and the chain rule written out).

        The local update of a pose is ``y -> e^dl exp([dw]x) (y - c) + c + L dtau`` about the
        centre ``c``, and the offset delta (*L*) moves by ``d delta``; with ``v = T(x) - c``
        and ``g`` the library SDF gradient at ``T(x)``, the scene-side residual's derivatives
        are ``(v x g, g.v - s S_scene(x), L g, -L)``; for a library sample ``y``, with
        ``u = y - c`` and ``h = R grad S_scene(T^-1 y)``, ``(h x u, s S_scene - h.u, -L h, L)``.
        All divided by ``L`` (residuals in reference lengths)."""
        cfg, L = self.cfg, self.L
        act = self.active
        k = len(act)
        idx = torch.tensor(act, device=self.xA.device)
        with torch.no_grad():
            R, t, s = (v[idx] for v in self.pose())
            d = self.offset()[idx] * L
            c = self.centre[idx]
        thr = cfg.inlier_threshold * L
        gA = self.gA
        yA = s[gA, None] * torch.einsum("nij,nj->ni", R[gA], self.xA.double()) + t[gA]
        if self.bidirectional:
            gB = self.gB
            yB = self.yB.double()
            xB = torch.einsum("nji,nj->ni", R[gB], yB - t[gB]) / s[gB, None]
            at_xB, at_yA = self._both(lambda: self.scene.sdf_and_gradient(xB.to(self.dtype)),
                                      lambda: self.library.sdf_and_gradient(yA.to(self.dtype)))
        else:
            at_yA = self.library.sdf_and_gradient(yA.to(self.dtype))
        slib, glib = (v.double() for v in at_yA)
        _check_finite(slib, "the library field (at the mapped scene samples)")
        ssA = s[gA] * self.sA.double()
        eA = slib - ssA - d[gA]
        v = yA - c[gA]
        JA = torch.cat([torch.linalg.cross(v, glib), ((glib * v).sum(1) - ssA)[:, None], L * glib,
                        torch.full_like(eA, -L)[:, None]], dim=1)
        wA = self.wA.double() if self.wA is not None else torch.ones_like(eA)
        cntA = _segment_sum(wA, gA, k)
        rows = [(eA, JA, wA / cntA.clamp(min=1)[gA], gA)]
        stats = torch.zeros(k, 7, dtype=torch.float64, device=eA.device)
        stats[:, 0] = _segment_sum(wA * eA.abs(), gA, k) / cntA.clamp(min=1)
        stats[:, 1] = float("nan")
        stats[:, 2] = stats[:, 5] = _segment_sum(wA * (eA.abs() <= thr).double(), gA, k)
        stats[:, 3] = stats[:, 6] = cntA
        q = Jq = aq = gq = None
        if self.bidirectional:
            ssc, gsc = (v.double() for v in at_xB)
            _check_finite(ssc, "the scene field (at the mapped library samples)")
            eB = s[gB] * ssc + d[gB] - self.sB.double()
            u = yB - c[gB]
            h = torch.einsum("nij,nj->ni", R[gB], gsc)
            JB = torch.cat([torch.linalg.cross(h, u), (s[gB] * ssc - (h * u).sum(1))[:, None], -L * h,
                            torch.full_like(eB, L)[:, None]], dim=1)
            wB = self._observed(xB, self._normals_B(R))
            wB = wB.double() if wB is not None else torch.ones_like(eB)
            cntB = _segment_sum(wB, gB, k)
            rows.append((eB, JB, wB / cntB.clamp(min=1)[gB], gB))
            stats[:, 1] = _segment_sum(wB * eB.abs(), gB, k) / cntB.clamp(min=1)
            stats[:, 2] += _segment_sum(wB * (eB.abs() <= thr).double(), gB, k)
            stats[:, 3] += cntB
            if cfg.regulariser_weight > 0:
                q, Jq, aq, gq = self._linear_regulariser(yA, v, stats)
        if q is None:
            z = eA.new_zeros(0)
            q, Jq, aq, gq = z.view(0, 3), z.view(0, 3, 8), z, gA.new_zeros(0)
        x, J, a, group = (torch.cat(parts) for parts in zip(*rows))
        return _Linear(x / L, J / L, a, group, q, Jq, aq, gq, stats)

    def _linear_regulariser(self, yA: torch.Tensor, v: torch.Tensor, stats: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The kept nearest-neighbour vectors of the regulariser, their Jacobians, weights and
        hypotheses; writes each hypothesis's trimmed mean into ``stats[:, 4]``."""
        L, parts = self.L, []
        for i, k in enumerate(self.active):
            sel = self.gA == i
            y = yA[sel]
            nn = self.nearest[i].query(y).to(y.device)
            diff = (y - self.B[k][nn].double()) / L
            d2 = (diff**2).sum(1)
            keep = max(1, math.floor(self.cfg.trim_fraction * d2.shape[0]))
            kept = torch.topk(d2, keep, largest=False, sorted=False).indices.sort().values
            stats[i, 4] = d2[kept].mean()
            vk = v[sel][kept]
            eye = torch.eye(3, dtype=vk.dtype, device=vk.device).expand(vk.shape[0], 3, 3)
            Jq = torch.cat([-_skew(vk), vk[:, :, None], L * eye, vk.new_zeros(vk.shape[0], 3, 1)], dim=2) / L
            w = torch.full((keep,), self.cfg.regulariser_weight / keep, dtype=vk.dtype, device=vk.device)
            parts.append((diff[kept], Jq, w, torch.full((keep,), i, dtype=torch.long, device=vk.device)))
        return tuple(torch.cat(p) for p in zip(*parts))  # type: ignore[return-value]

    def objective(self, lin: _Linear, alpha: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """(k,) the loss of :meth:`evaluate` from a linearisation, under the kernels (k,) given."""
        a, c = alpha[lin.group], scale[lin.group]
        nll = general_rho(lin.x, a, c) + torch.log(c) + log_partition(a)
        k = lin.stats.shape[0]
        return _segment_sum(lin.a * nll, lin.group, k) + _segment_sum(lin.aq * (lin.q**2).sum(1), lin.gq, k)

    def normal_equations(self, lin: _Linear, alpha: torch.Tensor, scale: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(k, 8, 8) H with the loss's own curvature ``max(rho'', 0)``, (k, 8, 8) H of the
        reweighting (``rho'/x``, a majoriser: never a smaller curvature) and the (k, 8) gradient
        g (:mod:`regnf.registration.irls`)."""
        k = lin.stats.shape[0]
        a, c = alpha[lin.group], scale[lin.group]
        W = barron_weight(lin.x, a, c)
        H_irls, g = segment_normal_equations(lin.J, lin.x, lin.a * W, lin.group, k)
        H_newton = (segment_gram(lin.J, lin.a * barron_curvature(lin.x, a, c), lin.group, k)
                    if self.cfg.lm_curvature == "newton" else H_irls)
        if lin.q.shape[0]:
            Jq = lin.Jq.reshape(-1, 8)
            Hq, gq = segment_normal_equations(Jq, lin.q.reshape(-1), 2.0 * lin.aq.repeat_interleave(3),
                                              lin.gq.repeat_interleave(3), k)
            H_newton, H_irls, g = H_newton + Hq, H_irls + Hq, g + gq
        return H_newton, H_irls, g

    def fit_kernels(self, lin: _Linear) -> tuple[torch.Tensor, torch.Tensor]:
        """(k,) alpha and c minimising the residuals' NLL; also set in ``self.kernel`` (reported)."""
        cfg = self.cfg
        alpha, scale = fit_kernel(lin.x, lin.a, lin.group, lin.stats.shape[0], cfg.alpha_lo, cfg.alpha_hi)
        self.kernel.assign(torch.tensor(self.active, device=alpha.device), alpha, scale)
        return alpha, scale

    def pose_state(self) -> tuple[torch.Tensor, ...]:
        """Clones of every pose parameter (for undoing a rejected step)."""
        return tuple(p.detach().clone() for p in (self.R0, self.t0, self.s0, self.w, self.log_s, self.tau,
                                                  self.delta))

    def restore_pose(self, state: tuple[torch.Tensor, ...], which: torch.Tensor) -> None:
        """Put the hypotheses ``which`` (K,) bool back to ``state``."""
        with torch.no_grad():
            for p, saved in zip((self.R0, self.t0, self.s0, self.w, self.log_s, self.tau, self.delta), state):
                p[which] = saved[which]

    def apply_step(self, step: torch.Tensor) -> None:
        """Move the active hypotheses by their local updates ``step`` (k, 8), re-basing each
        pose on the result: ``R0, t0, s0`` become the new pose and ``w, log_s, tau`` zero."""
        idx = torch.tensor(self.active, device=step.device)
        with torch.no_grad():
            R, t, s = (v[idx] for v in self.pose())
            c = self.centre[idx]
            E = torch.linalg.matrix_exp(_skew(step[:, :3]))
            e = torch.exp(step[:, 3])
            self.R0[idx] = E @ R
            self.s0[idx] = e * s
            self.t0[idx] = e[:, None] * (E @ (t - c)[..., None])[..., 0] + c + self.L * step[:, 4:7]
            for p in (self.w, self.log_s, self.tau):
                p[idx] = 0.0
            # The offset moves directly, kept inside its bound (the latent is its tanh preimage).
            m = self.cfg.max_offset
            if m > 0:
                bounded = ((self.offset()[idx] + step[:, 7]) / m).clamp(-1 + 1e-9, 1 - 1e-9)
                self.delta[idx] = m * torch.atanh(bounded)
            else:
                self.delta[idx] = self.delta[idx] + step[:, 7]

    def offset_at_bound(self) -> torch.Tensor:
        """(k,) sign (+1, -1) of the active hypotheses' offsets that sit at their bound, else 0."""
        m = self.cfg.max_offset
        delta = self.offset()[torch.tensor(self.active, device=self.delta.device)].detach()
        if m <= 0:
            return torch.zeros_like(delta)
        return torch.sign(delta) * (delta.abs() >= m * (1 - 1e-6)).to(delta.dtype)

    # -- convergence ------------------------------------------------------------------------
    def pose_snapshot(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(K, 3, 3) R, (K, 3) mapped centroid of A, (K,) s, detached."""
        with torch.no_grad():
            R, t, s = self.pose()
            c = s[:, None] * (R @ self.a_mean) + t
        return R, c, s

    def motion(self, previous: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
               symmetry: ObjectSymmetry | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(K,) rotation (rad), motion of the mapped centroid of A (*L*) and relative scale change
        of every hypothesis since ``previous`` (a :meth:`pose_snapshot`).

        For an object with a continuous ``symmetry`` a turn about its axis is no motion: the
        rotation is measured modulo those turns and the centroid by its height along the axis
        and its distance from it (the axis through the library bounds' centre): a round object
        can turn about its axis at a constant loss for every iteration
        (docs/decisions/registration-refinement.md)."""
        R0, c0, s0 = previous
        R1, c1, s1 = self.pose_snapshot()
        cos = ((R0.transpose(1, 2) @ R1).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
        angle = torch.arccos(cos.clamp(-1.0, 1.0))
        moved = (c1 - c0).norm(dim=1) / self.L
        if symmetry is not None and symmetry.order == 0:
            a = torch.as_tensor(np.asarray(symmetry.axis), dtype=c0.dtype, device=c0.device)
            a = a / a.norm()
            p = self.library.bounds.to(c0).mean(dim=0)
            h0, h1 = (c0 - p) @ a, (c1 - p) @ a
            r0 = (c0 - p - h0[:, None] * a).norm(dim=1)
            r1 = (c1 - p - h1[:, None] * a).norm(dim=1)
            moved = torch.hypot(h1 - h0, r1 - r0) / self.L
            Q = (R1 @ R0.transpose(1, 2)).cpu().numpy()
            axis = np.asarray(symmetry.axis, dtype=np.float64)
            angle = torch.tensor([symmetric_angle(q, axis, 0) for q in Q], dtype=angle.dtype,
                                 device=angle.device)
        return angle, moved, (s1 / s0 - 1).abs()

    def converged(self, previous: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> list[int]:
        """Active hypotheses whose pose moved less than the tolerances since ``previous``."""
        cfg = self.cfg
        angle, moved, ds = self.motion(previous)
        ok = (angle < cfg.convergence_rotation) & (moved < cfg.convergence_translation) \
            & (ds < cfg.convergence_scale)
        return [k for k in self.active if bool(ok[k])]

    # -- bookkeeping ------------------------------------------------------------------------
    def _leaves(self) -> list[torch.Tensor]:
        return [self.w, self.log_s, self.tau, self.delta, self.kernel.latent_alpha, self.kernel.latent_scale]

    def snapshot(self, k: int) -> None:
        """Hypothesis k is done: remember its parameters (Adam's momentum would move them)."""
        self.stopped[k] = {str(i): p.detach()[k].clone() for i, p in enumerate(self._leaves())}

    def deactivate(self, done: list[int]) -> None:
        """Stop querying the fields for the hypotheses in ``done``."""
        self.active = [a for a in self.active if a not in done]
        if self.active:
            self._rebuild()

    def restore_all(self) -> None:
        """Put every stopped hypothesis back at the parameters it stopped with; all active again."""
        with torch.no_grad():
            for k, saved in self.stopped.items():
                for i, p in enumerate(self._leaves()):
                    p[k] = saved[str(i)]
        self.stopped = {}
        self.active = list(range(self.K))
        self._rebuild()

    def transforms(self) -> list[SimilarityTransform]:
        with torch.no_grad():
            R, t, s = self.pose()
        R, t, s = R.cpu().numpy(), t.cpu().numpy(), s.cpu().numpy()
        return [SimilarityTransform(R[k].copy(), t[k].copy(), float(s[k])) for k in range(self.K)]


# -- public API ------------------------------------------------------------------------------


def refine_many(
    scene_field: Field,
    library_field: Field,
    A: torch.Tensor,
    B: torch.Tensor | None,
    inits: Sequence[SimilarityTransform],
    config: RefineConfig | None = None,
    device: torch.device | str | None = None,
    symmetry: ObjectSymmetry | None = None,
    workers: int | None = None,
) -> list[RefineResult]:
    """Refine K initial hypotheses at once (one batched pair of field queries per iteration).

    Parameters
    ----------
    scene_field, library_field : Field
        On one device; their parameters receive no gradient.
    A : (n, 3) float
        Surface samples of the object in the scene field frame.
    B : (m, 3) float or None
        Surface samples of the library object in the library field frame (ignored, and may be
        None, when ``config.bidirectional`` is False).
    inits : list of SimilarityTransform
        Initial scene -> library similarities, at least one.
    config : RefineConfig, optional
    device : torch device, optional
        Where to compute; it must be the fields' device (nothing is moved implicitly).
    symmetry : ObjectSymmetry, optional
        The library object's symmetry: Levenberg-Marquardt stops a hypothesis that reaches a
        better one's pose modulo it (``RefineConfig.lm_merge_rotation_deg``).
    workers : int, optional
        CPU threads for the pair of field queries, the scene's and the library's side by side
        (each on one thread, so the results are the same bits on any count); default: one per
        core torch may use here (:func:`~regnf.core.threads.worker_count`).

    Returns
    -------
    list of RefineResult
        One per hypothesis, in the order of ``inits``.
    """
    cfg = config or RefineConfig()
    dev = library_field.device
    if scene_field.device != dev:
        raise ValueError(f"the scene field is on {scene_field.device} and the library field on {dev}; "
                         "move both to one device")
    if device is not None and torch.device(device) != dev:
        raise ValueError(f"device {device} requested but the fields are on {dev}")
    _check_points(A, "A (scene samples)", dev)
    if cfg.bidirectional:
        _check_points(B, "B (library samples)", dev)
        if B.dtype != A.dtype:
            raise ValueError(f"A is {A.dtype} but B is {B.dtype}")
    inits = list(inits)
    if not inits:
        raise ValueError("refine_many needs at least one initial transform")
    for k, T in enumerate(inits):
        _check_transform(T, k)

    workers = worker_count(workers)  # before one_thread() sets torch's count to 1
    start = time.perf_counter()
    with _frozen(scene_field, library_field), one_thread():
        batch = _Batch(scene_field, library_field, A, B if cfg.bidirectional else None, inits, cfg, workers)
        K = len(inits)
        histories: list[list[dict]] = [[] for _ in range(K)]
        steps = [0] * K
        if cfg.optimizer == "lm":
            _run_lm(batch, histories, steps, symmetry)
        else:
            _run_adam(batch, histories, steps)
        # One more evaluation at the returned parameters, so the reported numbers describe them.
        batch.restore_all()
        with torch.no_grad():
            loss, stats = batch.evaluate()
        transforms = batch.transforms()
        offsets = batch.offset().detach().cpu().tolist()
    seconds = time.perf_counter() - start
    loss, stats = loss.cpu().numpy(), stats.cpu().numpy()
    return [
        RefineResult(
            transform=transforms[k],
            loss=float(loss[k]),
            mean_residual_A=float(stats[k, 0]),
            mean_residual_B=float(stats[k, 1]),
            inlier_fraction=float(stats[k, 2] / max(stats[k, 3], 1.0)),
            iterations=steps[k],
            history=histories[k],
            seconds=seconds,
            inlier_fraction_scene=float(stats[k, 5] / max(stats[k, 6], 1.0)),
            inlier_fraction_library=float((stats[k, 2] - stats[k, 5]) / max(stats[k, 3] - stats[k, 6], 1.0))
            if cfg.bidirectional else float("nan"),
            offset=float(offsets[k]),
        )
        for k in range(K)
    ]


def _adam(batch: _Batch) -> torch.optim.Adam:
    """Adam over the batch's pose, offset and kernel parameters, at the configured rates.

    Made only when Adam refines: torch's optimisers import its compiler (torch._dynamo) on
    first use, 1.4 s of the first registration in a process otherwise.
    """
    cfg = batch.cfg
    groups = [
        {"params": [batch.w], "lr": cfg.lr_rotation},
        {"params": [batch.tau], "lr": cfg.lr_translation},
        {"params": list(batch.kernel.parameters()), "lr": cfg.lr_kernel},
    ]
    if not cfg.fix_scale:
        groups.append({"params": [batch.log_s], "lr": cfg.lr_scale})
    if cfg.level_set_offset:
        groups.append({"params": [batch.delta], "lr": cfg.lr_offset})
    return torch.optim.Adam(groups)


def _run_adam(batch: _Batch, histories: list[list[dict]], steps: list[int]) -> None:
    """The paper's refinement: Adam on the pose, the offset and the kernel together."""
    cfg = batch.cfg
    opt = _adam(batch)
    previous = batch.pose_snapshot()
    for it in range(cfg.max_iterations):
        if not batch.active:
            break
        if it > 0 and cfg.resample_every > 0 and it % cfg.resample_every == 0:
            batch.resample()
        loss, stats = batch.evaluate()
        _check_finite(loss.detach(), f"the refinement loss (iteration {it})")
        opt.zero_grad(set_to_none=True)
        loss.sum().backward()
        _record(batch, histories, it, loss.detach(), stats)
        # Early stop on the transform just evaluated: it is the one returned, no step after.
        done = [k for i, k in enumerate(batch.active) if float(stats[i, 0]) < cfg.early_stop_residual * batch.L]
        if cfg.convergence_window > 0 and it % cfg.convergence_window == 0:
            done += [k for k in batch.converged(previous) if k not in done] if it > 0 else []
            previous = batch.pose_snapshot()
        if cfg.prune_after > 0 and it == cfg.prune_after:
            done += [k for k in _trailing(batch, stats) if k not in done]
        for k in done:
            batch.snapshot(k)
        opt.step()
        for k in batch.active:
            if k not in done:
                steps[k] += 1
        if done:
            batch.deactivate(done)


def _trailing(batch: _Batch, stats: torch.Tensor, best: float = float("-inf")) -> list[int]:
    """Active hypotheses whose inlier fraction trails the best by more than ``prune_margin``
    (the best of the active ones and ``best``, that of the stopped ones)."""
    frac = (stats[:, 2] / stats[:, 3].clamp(min=1)).tolist()
    if len(batch.active) + (best > float("-inf")) < 2:
        return []
    best = max(frac + [best])
    return [k for i, k in enumerate(batch.active) if frac[i] < best - batch.cfg.prune_margin]


def _merged(batch: _Batch, fraction: list[float], symmetry: ObjectSymmetry | None) -> list[int]:
    """Active hypotheses within the ``lm_merge_*`` tolerances of one with a higher inlier
    ``fraction`` (K,) (the latest of each hypothesis, running or stopped; ties: the earlier
    one stays)."""
    cfg = batch.cfg
    if cfg.lm_merge_rotation_deg <= 0 or batch.K < 2:
        return []
    R, c, s = (v.detach().cpu().numpy() for v in batch.pose_snapshot())
    limit = math.radians(cfg.lm_merge_rotation_deg)
    return [k for k in batch.active
            if any(same_pose(R[k], R[j], float(s[k]), float(s[j]), float(np.linalg.norm(c[k] - c[j])),
                             symmetry, limit, cfg.lm_merge_scale, cfg.lm_merge_shift * batch.L)
                   for j in range(batch.K) if j != k and (fraction[j], -j) > (fraction[k], -k))]


def _run_lm(batch: _Batch, histories: list[list[dict]], steps: list[int],
            symmetry: ObjectSymmetry | None = None) -> None:
    """Levenberg-Marquardt on the iteratively reweighted problem (:mod:`regnf.registration.irls`).

    Each iteration fits every active hypothesis's kernel (alpha, c) to its residuals, solves the
    damped normal equations for a local update, and keeps the update where it lowers that
    hypothesis's loss (same kernel) by a fair share of what the model predicted, else undoes it
    and raises the damping. A hypothesis stops when a step would move it less than
    ``lm_step_tolerance``, when no damping finds a lower loss, on the paper's residual stop, or
    when pruned.
    """
    cfg, K = batch.cfg, batch.K
    dev = batch.xA.device
    free = torch.tensor([True] * 3 + [not cfg.fix_scale] + [True] * 3 + [cfg.level_set_offset], device=dev)
    mu = torch.full((K,), cfg.lm_damping, dtype=torch.float64, device=dev)
    nu = torch.full((K,), 2.0, dtype=torch.float64, device=dev)
    cautious = torch.full((K,), cfg.lm_curvature == "irls", device=dev)  # use the majoriser
    fraction = torch.full((K,), -1.0, dtype=torch.float64, device=dev)  # latest inlier fraction
    lin: _Linear | None = None
    for it in range(cfg.lm_max_iterations):
        if not batch.active:
            break
        if it > 0 and cfg.lm_resample_every > 0 and it % cfg.lm_resample_every == 0 \
                and it // cfg.lm_resample_every <= cfg.lm_resamples:
            batch.resample()
            lin = None
        if lin is None:
            lin = batch.linearise()
        alpha, scale = batch.fit_kernels(lin)
        loss = batch.objective(lin, alpha, scale)
        _check_finite(loss, f"the refinement loss (iteration {it})")
        _record(batch, histories, it, loss, lin.stats)
        act = torch.tensor(batch.active, device=dev)
        done = [k for i, k in enumerate(batch.active)
                if float(lin.stats[i, 0]) < cfg.early_stop_residual * batch.L]
        fraction[act] = lin.stats[:, 2] / lin.stats[:, 3].clamp(min=1)
        if cfg.lm_prune_after > 0 and it == cfg.lm_prune_after:
            stopped = [float(fraction[k]) for k in range(K) if k not in batch.active and fraction[k] >= 0]
            done += [k for k in _trailing(batch, lin.stats, max(stopped, default=float("-inf")))
                     if k not in done]
        if cfg.lm_prune_after > 0 and it >= cfg.lm_prune_after:
            done += [k for k in _merged(batch, fraction.tolist(), symmetry) if k not in done]
        H_newton, H_irls, g = batch.normal_equations(lin, alpha, scale)
        H = torch.where(cautious[act][:, None, None], H_irls, H_newton)
        state, before = batch.pose_state(), batch.pose_snapshot()
        offset_before = batch.offset()[act].detach().clone()
        step = damped_step(H, g, mu[act], free)
        # An offset at its bound that the step would push further out stays there (active set).
        held = batch.offset_at_bound() * step[:, 7] > 0
        if bool(held.any()):
            pinned = free.expand(len(batch.active), -1).clone()
            pinned[held, 7] = False
            step = torch.where(held[:, None], damped_step(H, g, mu[act], pinned), step)
        batch.apply_step(step)
        trial = batch.linearise()
        # Gain ratio: the loss's decrease over the decrease the quadratic model predicted.
        predicted = -((g * step).sum(1) + 0.5 * torch.einsum("ki,kij,kj->k", step, H, step))
        gain = (loss - batch.objective(trial, alpha, scale)) / predicted.clamp(min=1e-300)
        accepted = (gain > 1e-3) & (predicted > 0)
        # The step's size, accepted or not: a step this small that does not help is a minimum.
        angle, moved, ds = batch.motion(before, symmetry)
        tol = cfg.lm_step_tolerance
        # The offset is part of the step: a step that only moves the offset is not small.
        small = (angle < tol) & (moved < tol) & (ds < tol)
        small[act] &= (batch.offset()[act].detach() - offset_before).abs() < tol
        rejected = torch.zeros(K, dtype=torch.bool, device=dev)
        rejected[act] = ~accepted
        batch.restore_pose(state, rejected)
        # Nielsen's damping update: shrink by up to 3 after a good step, grow ever faster
        # after successive bad ones; the first bad Newton step only switches to the majoriser.
        retry = ~accepted & ~cautious[act]
        grow = ~accepted & cautious[act]
        shrink = torch.clamp(1 - (2 * gain - 1) ** 3, min=1 / 3)
        mu[act] = torch.where(accepted, (mu[act] * shrink).clamp(min=1e-12),
                              torch.where(grow, mu[act] * nu[act], mu[act]))
        nu[act] = torch.where(accepted, torch.full_like(nu[act], 2.0), torch.where(grow, nu[act] * 2, nu[act]))
        cautious[act] = retry | (grow & (cfg.lm_curvature == "irls")) | (accepted & (cfg.lm_curvature == "irls"))
        lin = lin.merge(trial, accepted)
        for k in batch.active:
            steps[k] += 1
            if k not in done and (bool(small[k]) or float(mu[k]) > 1e8):
                done.append(k)
        if done:
            keep = torch.tensor([k not in done for k in batch.active], device=dev)
            batch.deactivate(done)
            lin = lin.select(keep) if batch.active else None


def _record(batch: _Batch, histories: list[list[dict]], it: int, loss: torch.Tensor,
            stats: torch.Tensor) -> None:
    idx = torch.tensor(batch.active, device=loss.device)
    with torch.no_grad():
        s = (torch.exp(batch.log_s) * batch.s0)[idx]
        table = torch.stack([loss.double(), stats[:, 0].double(), stats[:, 1].double(),
                             batch.kernel.alpha[idx].double(), batch.kernel.scale[idx].double(), s,
                             stats[:, 4].double(), batch.offset()[idx].double()], dim=1).cpu().numpy()
    for i, k in enumerate(batch.active):
        row = table[i]
        histories[k].append({
            "iteration": it, "loss": float(row[0]), "mean_residual_A": float(row[1]),
            "mean_residual_B": float(row[2]), "alpha": float(row[3]), "c": float(row[4]),
            "s": float(row[5]), "regulariser": float(row[6]), "offset": float(row[7]),
            "n_A": int(batch.A[k].shape[0]), "n_B": int(batch.B[k].shape[0]) if batch.B else 0,
        })


def refine(
    scene_field: Field,
    library_field: Field,
    A: torch.Tensor,
    B: torch.Tensor | None,
    T0: SimilarityTransform,
    config: RefineConfig | None = None,
    device: torch.device | str | None = None,
) -> RefineResult:
    """Refine one scene -> library similarity by bidirectional SDF alignment.

    Parameters
    ----------
    scene_field, library_field : Field
        On one device.
    A : (n, 3) float
        Scene surface samples, scene field frame.
    B : (m, 3) float or None
        Library surface samples, library field frame (None allowed when not bidirectional).
    T0 : SimilarityTransform
        Initial scene -> library similarity.
    config : RefineConfig, optional
    device : torch device, optional
        Must be the fields' device.

    Returns
    -------
    RefineResult
    """
    return refine_many(scene_field, library_field, A, B, [T0], config, device)[0]
