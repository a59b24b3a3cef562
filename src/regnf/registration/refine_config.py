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
    """Most Adam steps, learning rates constant (*paper*: 200; docs/decisions/registration-refinement.md)."""
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
    """Initial kernel scale c, *L*: the surface tolerance (*paper*: 1; docs/decisions/registration-refinement.md)."""
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
    """Weight w of the trimmed scene -> library nearest-neighbour term (docs/decisions/registration-refinement.md)."""
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
    """Stop window, Adam iterations, for the tolerances below; 0 disables (docs/decisions/registration-refinement.md)."""
    convergence_rotation_deg: float = math.degrees(1e-3)
    """Rotation tolerance of that stop, degrees (a thousandth of a radian)."""
    convergence_translation: float = 1e-3
    """Tolerance on the motion of the mapped scene samples' centroid, *L*."""
    convergence_scale: float = 1e-3
    """Relative scale tolerance."""
    prune_after: int = 10
    """Adam iteration at which hypotheses trailing the best inlier fraction by > ``prune_margin`` stop; 0 disables."""
    prune_margin: float = 0.1
    """See ``prune_after``."""
    level_set_offset: bool = True
    """Learn an offset delta of the scene SDF, ``s S_scene + delta L`` (docs/decisions/registration-refinement.md)."""
    lr_offset: float = 0.003
    """Adam learning rate of delta, *L*."""
    max_offset: float = 0.01
    """Bound on |delta|, *L* (``delta = max_offset tanh(d)``); 0: unbounded (docs/decisions/registration-refinement.md)."""
    use_visibility: bool = True
    """Weight residuals by how well the scene's training views observed them (docs/decisions/registration-refinement.md)."""
    visibility_lookahead: float = 3.0
    """Library samples' visibility is read this many grid voxels out; 0: at them (docs/decisions/registration-refinement.md)."""

    optimizer: Literal["lm", "adam"] = "lm"
    """``lm``: Levenberg-Marquardt; ``adam``: the paper's Adam (docs/decisions/registration-refinement.md)."""
    lm_max_iterations: int = 30
    """Most Levenberg-Marquardt iterations (``optimizer="lm"``); ``max_iterations`` caps Adam."""
    lm_resample_every: int = 3
    """Resample every this many LM iterations (Adam: ``resample_every``); 0 never resamples."""
    lm_resamples: int = 2
    """Resampling rounds at most, then fixed samples (docs/decisions/registration-refinement.md)."""
    lm_prune_after: int = 6
    """LM iteration of the pruning (``prune_margin``); 0 disables it and merging (docs/decisions/registration-refinement.md)."""
    lm_merge_rotation_deg: float = 5.0
    """Merge distance in rotation, degrees modulo symmetry; 0 disables merging (docs/decisions/registration-refinement.md)."""
    lm_merge_scale: float = 0.05
    """See ``lm_merge_rotation_deg``: relative scale."""
    lm_merge_shift: float = 0.1
    """See ``lm_merge_rotation_deg``: *L*."""
    lm_step_tolerance: float = 1e-4
    """LM converged when a step moves less than this: rotation (rad), centroid of A and offset (*L*), relative scale."""
    lm_damping: float = 1e-3
    """Initial Levenberg-Marquardt damping mu, relative to the diagonal, then Nielsen's gain-ratio update."""

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
