"""SLAM-like camera pose error: per-frame jitter plus a random-walk drift along the path.

A capture made with pose error stores the perturbed poses (what an RGB-D SLAM system would
report) while its images were rendered from the true ones. Each pose's error is a rigid
motion about its own camera centre: the centre moves by a translation error ``e_t`` and the
axes turn by a rotation error ``R_e`` (world axes), so ``|e_t|`` and the angle of ``R_e`` are
the pose's position and orientation errors as an absolute-trajectory evaluation measures them.

The drift is a Gaussian random walk that starts at zero on the first frame (SLAM anchors the
map there) and is scaled so that its last frame's error is exactly the configured magnitude;
the jitter is independent per frame, with the configured root-mean-square magnitude.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class PoseNoiseConfig:
    """Magnitudes of the pose error (all 0: the true poses)."""

    jitter_m: float = 0.0
    """Root-mean-square length of each frame's independent position error, metres."""
    jitter_deg: float = 0.0
    """Root-mean-square angle of each frame's independent orientation error, degrees."""
    drift_m: float = 0.0
    """Position error of the random-walk drift at the last frame, metres."""
    drift_deg: float = 0.0
    """Orientation error of the random-walk drift at the last frame, degrees."""


def random_walk(n: int, end_norm: float, rng: np.random.Generator) -> np.ndarray:
    """A 3-D Gaussian random walk from 0 whose last point has length ``end_norm``.

    Parameters
    ----------
    n : int
        Number of points (frames).
    end_norm : float
        Length of the last point; 0 gives all zeros (as does ``n == 1``).
    rng : numpy.random.Generator

    Returns
    -------
    (n, 3) float64
        ``walk[0] == 0`` and ``|walk[-1]| == end_norm``.
    """
    steps = rng.standard_normal((max(n - 1, 0), 3))
    walk = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])[:n]
    end = float(np.linalg.norm(walk[-1])) if n else 0.0
    return walk * (end_norm / end) if end > 0 else np.zeros((n, 3))


def perturb_poses(c2w: np.ndarray, config: PoseNoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """The poses a SLAM system would report for the true camera-to-world poses ``c2w``.

    Parameters
    ----------
    c2w : (n, 4, 4) float
        True rigid camera-to-world poses, metres.
    config : PoseNoiseConfig
        Jitter and drift magnitudes.
    rng : numpy.random.Generator
        Draws the drift walks (position, then orientation) and then the jitter.

    Returns
    -------
    (n, 4, 4) float64
        Rigid poses: centre ``t + drift_t + jitter_t``, rotation ``R_jitter R_drift R``.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    n = len(c2w)
    drift_t = random_walk(n, config.drift_m, rng)
    drift_r = random_walk(n, np.radians(config.drift_deg), rng)
    # Per-axis standard deviation s gives a root-mean-square length of s * sqrt(3).
    jitter_t = rng.standard_normal((n, 3)) * (config.jitter_m / np.sqrt(3.0))
    jitter_r = rng.standard_normal((n, 3)) * (np.radians(config.jitter_deg) / np.sqrt(3.0))
    turn = (Rotation.from_rotvec(jitter_r) * Rotation.from_rotvec(drift_r)).as_matrix()
    out = c2w.copy()
    out[:, :3, :3] = turn @ c2w[:, :3, :3]
    out[:, :3, 3] = c2w[:, :3, 3] + drift_t + jitter_t
    return out


def pose_errors(estimated: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame position error (metres) and orientation error (degrees) of ``estimated``.

    Parameters
    ----------
    estimated, true : (n, 4, 4) float
        Camera-to-world poses.

    Returns
    -------
    position : (n,) float64
        ``|t_est - t_true|``.
    orientation : (n,) float64
        Angle of ``R_est R_true^T``, degrees.
    """
    estimated, true = np.asarray(estimated, np.float64), np.asarray(true, np.float64)
    position = np.linalg.norm(estimated[:, :3, 3] - true[:, :3, 3], axis=1)
    rel = estimated[:, :3, :3] @ np.swapaxes(true[:, :3, :3], 1, 2)
    orientation = np.degrees(Rotation.from_matrix(rel).magnitude())
    return position, orientation
