"""Settings and results of the bidirectional SDF refinement (:mod:`regnf.registration.refinement`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.registration.transform import SimilarityTransform


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
    convergence_rotation_deg: float = math.degrees(1e-3)
    """Rotation tolerance of that stop, degrees (a thousandth of a radian)."""
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
    damped Newton step converges in far fewer iterations than Adam at the paper's rates;
    docs/decisions/registration-refinement.md.)"""
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
                raise RegnfError(f"RefineConfig.{name} must be finite and > 0, got {v}")
        if self.optimizer not in ("lm", "adam"):
            raise RegnfError(f"RefineConfig.optimizer must be 'lm' or 'adam', got {self.optimizer!r}")
        if not (math.isfinite(self.lm_step_tolerance) and self.lm_step_tolerance > 0
                and math.isfinite(self.lm_damping) and self.lm_damping > 0):
            raise RegnfError("RefineConfig.lm_step_tolerance and lm_damping must be finite and > 0")
        for name in ("max_iterations", "resample_every", "max_samples", "lm_max_iterations",
                     "lm_resample_every", "lm_resamples", "lm_prune_after"):
            if int(getattr(self, name)) < 0:
                raise RegnfError(f"RefineConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.regulariser_weight) and self.regulariser_weight >= 0):
            raise RegnfError(f"RefineConfig.regulariser_weight must be >= 0, got {self.regulariser_weight}")
        for name in ("lm_merge_rotation_deg", "lm_merge_scale", "lm_merge_shift"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise RegnfError(f"RefineConfig.{name} must be finite and >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.visibility_lookahead) and self.visibility_lookahead >= 0):
            raise RegnfError(f"RefineConfig.visibility_lookahead must be >= 0, got {self.visibility_lookahead}")
        if not (math.isfinite(self.max_offset) and self.max_offset >= 0):
            raise RegnfError(f"RefineConfig.max_offset must be >= 0, got {self.max_offset}")
        if not 0.0 < self.trim_fraction <= 1.0:
            raise RegnfError(f"RefineConfig.trim_fraction must be in (0, 1], got {self.trim_fraction}")
        if not self.early_stop_residual >= 0:
            raise RegnfError(f"RefineConfig.early_stop_residual must be >= 0, got {self.early_stop_residual}")
        if not 0.0 <= self.alpha_lo < self.alpha_hi <= 2.0:
            raise RegnfError(f"need 0 <= alpha_lo < alpha_hi <= 2, got ({self.alpha_lo}, {self.alpha_hi})")


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
