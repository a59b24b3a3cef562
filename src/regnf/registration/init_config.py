"""Settings of the registration's initialisation (:mod:`regnf.registration.initialisation`):
features, RANSAC, ICP and the choice of hypotheses."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from regnf.core.errors import RegnfError


@dataclass(frozen=True)
class InitConfig:
    """Settings of :func:`~regnf.registration.initialisation.initial_hypotheses` and
    :func:`~regnf.registration.initialisation.fgr_baseline`.

    Lengths in "voxels" are multiples of ``voxel_size``, itself a fraction of the library
    cloud's size (its largest AABB side), i.e. absolute lengths in the normalised frame.
    """

    voxel_size: float = 0.025
    """FPFH / RANSAC voxel, fraction of the library object's size (*paper*: 0.025)."""
    use_field_normals: bool = True
    """Use the samples' SDF normals (consistent, outward); False: Open3D estimates them."""
    normal_radius_voxels: float = 2.0
    """Normal estimation radius (only when ``use_field_normals`` is False) (*paper*: 2)."""
    normal_max_nn: int = 30
    """Neighbours of the normal estimation (only when ``use_field_normals`` is False)."""
    feature_radius_voxels: float = 5.0
    """FPFH radius (*paper*: 5)."""
    feature_max_nn: int = 100
    """FPFH neighbours (*paper*: 100)."""
    scale_estimate: Literal["rms", "percentile"] = "rms"
    """Scale pre-estimate: ratio of RMS radii, or of a percentile of the radii."""
    scale_percentile: float = 90.0
    """Percentile of the distances to the centroid used by ``scale_estimate='percentile'``."""
    ransac_distance_voxels: float = 1.5
    """RANSAC inlier distance and distance-checker threshold."""
    ransac_n: int = 4
    """Correspondences per RANSAC sample (*paper*: 4)."""
    edge_length_ratio: float = 0.9
    """Edge-length checker similarity (*paper*: 0.9)."""
    mutual_filter: bool = True
    """Only mutual nearest-neighbour matches (all if those give none) (docs/decisions/registration-initialisation.md)."""
    ransac_max_iteration: int = 100_000
    """RANSAC iterations at most per run."""
    ransac_confidence: float = 0.999
    """RANSAC stops early at this confidence (a probability: must be < 1)."""
    ransac_runs: int = 4
    """RANSAC runs, each on the matches the earlier hypotheses leave unexplained."""
    ransac_followup_iteration: int = 25_000
    """Iterations at most of runs 1, 2, ... (secondary modes; run 0 gets the full budget)."""
    min_matches: int = 20
    """A run needs at least this many remaining feature matches."""
    icp_method: Literal["point_to_point", "point_to_plane"] = "point_to_point"
    """ICP refinement; point-to-point estimates the scale too, point-to-plane keeps it."""
    icp_distance_voxels: float = 1.0
    """ICP correspondence distance; also the inlier distance of fitness and RMSE."""
    icp_max_iteration: int = 100
    """ICP iterations at most."""
    icp_coarse_voxels: float = 2.0
    """Voxels of the coarse ICP pass every start gets first; 0: none (docs/decisions/registration-initialisation.md)."""
    icp_coarse_relative_change: float = 1e-4
    """The coarse ICP stops when fitness and inlier RMSE change relatively less than this."""
    icp_relative_change: float = 1e-5
    """ICP stop: relative change of fitness and inlier RMSE below this (docs/decisions/registration-initialisation.md)."""
    max_scale_ratio: float = 2.0
    """Hypotheses whose scale differs from the pre-estimate by more than this factor go."""
    top_k: int = 4
    """Hypotheses kept for refinement after screening the ``candidates`` (without screening: returned at most)."""
    min_rotation_deg: float = 15.0
    """Kept hypotheses differ pairwise by at least this geodesic angle, or in scale or place."""
    min_scale_change: float = 0.1
    """... or their scales differ by at least this fraction, ..."""
    min_shift: float = 0.1
    """... or they put the library object's centre at least this fraction of its size apart."""
    upright_yaws: int = 24
    """Upright yaw starts a turn (over one symmetry period); 0: RANSAC only (docs/decisions/registration-initialisation.md)."""
    candidates: int = 12
    """Distinct ICP results handed to the SDF screening, which keeps the ``top_k`` best for refinement."""
    fgr_distance_voxels: float = 0.5
    """FGR's maximum correspondence distance (Open3D's example: 0.5 voxel)."""
    seed: int = 0
    """Seed of run 0; run r uses ``seed + r``."""

    def __post_init__(self) -> None:
        if not 0 < self.ransac_confidence < 1:
            raise RegnfError(
                f"ransac_confidence is a probability in (0, 1), got {self.ransac_confidence} "
                "(Open3D clamps 1 and above, then always runs every iteration)"
            )
        if self.voxel_size <= 0 or self.feature_radius_voxels <= 0 or self.icp_distance_voxels <= 0:
            raise RegnfError(
                "voxel_size, feature_radius_voxels and icp_distance_voxels must be > 0"
            )
        if self.icp_coarse_voxels < 0 or not (self.icp_relative_change > 0
                                               and self.icp_coarse_relative_change > 0):
            raise RegnfError("icp_coarse_voxels must be >= 0 and the ICP relative changes > 0")
        if self.ransac_n < 3 or self.ransac_runs < 1 or self.top_k < 1:
            raise RegnfError("ransac_n must be >= 3, ransac_runs and top_k >= 1")
        if self.upright_yaws < 0 or self.candidates < self.top_k:
            raise RegnfError("upright_yaws must be >= 0 and candidates >= top_k")
        if min(self.ransac_max_iteration, self.ransac_followup_iteration) < 1:
            raise RegnfError("RANSAC iteration budgets must be >= 1")
        if not (self.min_scale_change >= 0 and self.min_shift >= 0):
            raise RegnfError("min_scale_change and min_shift must be >= 0")
        if self.max_scale_ratio <= 1:
            raise RegnfError(f"max_scale_ratio must be > 1, got {self.max_scale_ratio}")
        if self.scale_estimate not in ("rms", "percentile"):
            raise RegnfError(f"unknown scale_estimate {self.scale_estimate!r}")
        if self.icp_method not in ("point_to_point", "point_to_plane"):
            raise RegnfError(f"unknown icp_method {self.icp_method!r}")
