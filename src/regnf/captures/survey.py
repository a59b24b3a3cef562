"""A quick look at a capture in its metric world: camera centres and axes, and a subsample of its depth.

What the up estimate (:mod:`regnf.captures.up_axis`), the room/object choice
(:mod:`regnf.captures.scene_kind`) and ``regnf inspect-capture`` read; training reads every
pixel instead (:mod:`regnf.observations.rgbd_samples`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from regnf.captures.metric import depth_points
from regnf.captures.model import Capture, similarity_scale
from regnf.captures.selection import evenly_spaced

SURVEY_FRAMES = 24
"""Frames (evenly spaced) whose depth the survey reads: enough to see the floor of a room scan."""


def metric_poses(capture: Capture) -> np.ndarray:
    """(n, 4, 4) float64 OpenCV camera-to-world of every frame in metres (rotations orthonormal).

    The vectorised :meth:`regnf.captures.model.Capture.camtoworld_metres`.
    """
    poses = np.stack([np.asarray(f.camtoworld, dtype=np.float64) for f in capture.frames])
    A = np.asarray(capture.worldtogt, dtype=np.float64)[:3, :3]
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, :3] = (A / similarity_scale(capture.worldtogt)) @ poses[:, :3, :3]
    out[:, :3, 3] = poses[:, :3, 3] @ A.T + capture.worldtogt[:3, 3]
    return out


def survey_frames(capture: Capture, limit: int = SURVEY_FRAMES) -> list[int]:
    """Indices of at most ``limit`` frames with depth, evenly spaced over the capture."""
    with_depth = [i for i, f in enumerate(capture.frames) if f.depth_path is not None]
    return [with_depth[k] for k in evenly_spaced(len(with_depth), limit)]


def depth_cloud(capture: Capture, frames: Sequence[int], poses: np.ndarray | None = None) -> np.ndarray:
    """(m, 3) float64 world points in metres of a subsample of the depth of ``frames``.

    Parameters
    ----------
    capture : Capture
    frames : sequence of int
        Frames to read (each with depth).
    poses : (n, 4, 4) float, optional
        :func:`metric_poses` of ``capture``, if already computed.

    Raises
    ------
    CaptureError
        An unreadable or invalid depth file (:meth:`regnf.captures.model.Capture.depth`).
    """
    poses = metric_poses(capture) if poses is None else poses
    clouds = [np.zeros((0, 3))]
    for i in frames:
        depth = capture.depth(i)
        if depth is not None:
            # Pixels (and so K) are the same in metres; only depth scales.
            frame = capture.frames[i]
            clouds.append(depth_points(depth * capture.scale, frame.intrinsics, poses[i], frame.distortion))
    return np.concatenate(clouds)
