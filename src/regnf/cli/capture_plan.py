"""What ``regnf train`` decides about a capture before it trains: frames, memory, up, preset.

In that order, so that a capture too large for memory is refused before any depth is read
(:func:`regnf.observations.sample_memory.check_training_memory`), and the depth the up
estimate and the preset choice need is read once, from a few frames (:mod:`regnf.captures.survey`).
``regnf inspect-capture`` shows the same up and preset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regnf.captures.model import Capture
from regnf.captures.scene_kind import SceneKind, scene_kind
from regnf.captures.selection import select_frames
from regnf.captures.survey import depth_cloud, metric_poses, survey_frames
from regnf.captures.up_axis import UpEstimate, parse_up, resolve_up
from regnf.observations.sample_memory import check_training_memory


@dataclass
class TrainingPlan:
    """The frames, up and kind of field ``regnf train`` trains from a capture."""

    indices: list[int]
    """Training frames (:func:`regnf.captures.selection.select_frames`)."""
    up: UpEstimate
    """Up of the capture's metric world (recorded in the field's provenance)."""
    kind: SceneKind
    """``scene`` or ``object``: the preset, and why."""


def needs_survey(capture: Capture, up: str, preset: str) -> bool:
    """Whether the up or the preset must be read off the capture's depth."""
    up_from_depth = parse_up(up) is None and capture.up is None
    kind_from_depth = preset == "auto" and capture.meta.get("kind") not in ("scene", "object")
    return up_from_depth or kind_from_depth


def up_and_kind(capture: Capture, up: str = "auto", preset: str = "auto",
                points: np.ndarray | None = None) -> tuple[UpEstimate, SceneKind]:
    """``--up`` and ``--preset`` resolved for ``capture`` (``auto``: from the capture).

    ``points`` (m, 3) are depth points in metres already read; None: those of a few frames
    are read where the up or the preset needs them (:func:`needs_survey`).

    Raises
    ------
    ValueError
        An ``up`` not in :data:`regnf.captures.up_axis.UP_CHOICES`.
    CaptureError
        An unreadable or invalid depth file among the surveyed frames.
    """
    poses = metric_poses(capture)
    if points is None and needs_survey(capture, up, preset):
        points = depth_cloud(capture, survey_frames(capture), poses)
    resolved = resolve_up(capture, up, points)
    if preset != "auto":
        kind = SceneKind(preset, "given by --preset")
    else:
        kind = scene_kind(capture, poses[:, :3, 3], np.zeros((0, 3)) if points is None else points)
    return resolved, kind


def plan_training(capture: Capture, up: str = "auto", preset: str = "auto", stride: int = 1,
                  max_frames: int | None = None, pixel_stride: int = 1) -> TrainingPlan:
    """Select the frames, check the memory, then resolve the up and the preset.

    Raises
    ------
    ValueError
        A bad ``stride``, ``max_frames`` or ``up`` (the message names the option).
    regnf.core.preflight.PreflightError
        Training would need more memory than is free (before any depth is read).
    CaptureError
        An unreadable or invalid depth file among the surveyed frames.
    """
    parse_up(up)  # a bad value is refused before anything is read
    indices = select_frames(capture.train_indices(), stride, max_frames)
    check_training_memory(str(capture.root), len(indices), capture.height, capture.width, pixel_stride)
    resolved, kind = up_and_kind(capture, up, preset)
    return TrainingPlan(indices, resolved, kind)


CELL_WARN_M = 0.04
"""Finest grid cell, metres, beyond which ``regnf train`` warns that the capture is too large
for one field (the benchmark's rooms get about 2 cm)."""


def cell_size_warning(capture: Capture, finest_resolution: int) -> str | None:
    """A warning line when the field's finest cell over ``capture`` would exceed :data:`CELL_WARN_M`.

    The extent is the largest side of the capture's scene box in metres, which the field's
    bounds never exceed; ``finest_resolution`` is the preset's cells along it.
    """
    aabb = np.asarray(capture.scene_box["aabb"], dtype=np.float64)
    extent = capture.scale * float(np.max(aabb[1] - aabb[0]))
    cell = extent / finest_resolution
    if cell <= CELL_WARN_M:
        return None
    return (f"{capture.root}: the capture is {extent:.1f} m across; {finest_resolution} finest cells make "
            f"cells of {100 * cell:.1f} cm (the benchmark's rooms get about 2 cm), so parts "
            f"thinner than about {200 * cell:.0f} cm blur; train a part of it (--max-frames, or a capture "
            "of one room) for a finer field")
