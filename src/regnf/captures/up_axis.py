"""The up direction of a capture's metric world: documented by its format, or estimated from it.

In order: the format's convention (:attr:`regnf.captures.model.Capture.up`: regnf's own
captures are +Z); else the normal of the floor, the largest plane among the back-projected
depth points that is within :data:`FLOOR_MAX_TILT_DEG` of the cameras' mean up and lies below
every camera; else the cameras' mean up vector (``-y`` of the OpenCV camera axes: a hand-held
or robot camera is mostly held level). A user's ``--up`` overrides all three (:func:`resolve_up`).
The floor search's constants and why: docs/decisions/up_axis.md.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, get_args

import numpy as np

from regnf.captures.model import Capture
from regnf.captures.survey import depth_cloud, metric_poses, survey_frames
from regnf.core.errors import RegnfError

UpChoice = Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z", "x", "y", "z"]
"""The type of an ``--up`` option."""

UP_CHOICES: tuple[str, ...] = get_args(UpChoice)
"""Values of ``--up``: ``auto`` (the format's convention, else estimated) or an axis (``z`` = ``+z``)."""

FLOOR_MAX_TILT_DEG = 30.0
"""A floor's normal lies within this many degrees of the cameras' mean up."""

FLOOR_TOLERANCE_M = 0.03
"""A depth point within this many metres of a plane lies on it (a sensor's noise at a few metres)."""

FLOOR_MIN_SHARE = 0.03
"""A plane is a floor only if at least this share of the surveyed depth points lie on it."""

FLOOR_DRAW_SHARE = 0.2
"""Planes are drawn through points among this lowest share along the cameras' mean up: the floor
is the lowest large surface, and among all points of a room scan it may hold only a few per cent."""

FLOOR_POINTS = 20_000
"""Depth points the floor search looks at (a seeded random subset)."""

FLOOR_HYPOTHESES = 512
"""Planes through three random points tried by the floor search."""

FLOOR_SEED = 0
"""Seed of the floor search: the same capture gives the same up on every run."""


class UpEstimate(NamedTuple):
    """The up direction of a capture and where it came from."""

    direction: np.ndarray
    """(3,) float64 unit vector in the capture's metric world."""
    source: str
    """``format`` (the format's convention), ``floor``, ``cameras`` or ``option`` (``--up``)."""
    detail: str
    """How it was found, in words, for the command's output."""


def parse_up(value: str) -> np.ndarray | None:
    """The axis ``value`` names (:data:`UP_CHOICES`) as a (3,) float64 unit vector; None for ``auto``.

    Raises
    ------
    ValueError
        Not one of :data:`UP_CHOICES`.
    """
    text = value.strip().lower()
    if text not in UP_CHOICES:
        raise RegnfError(f"--up {value}: expected one of {', '.join(UP_CHOICES[:7])}")
    if text == "auto":
        return None
    sign = -1.0 if text.startswith("-") else 1.0
    out = np.zeros(3)
    out["xyz".index(text[-1])] = sign
    return out


def up_text(direction: np.ndarray) -> str:
    """``+Z`` for an axis, else ``(0.02, -0.01, 1.00)``."""
    d = np.asarray(direction, dtype=np.float64)
    axis = int(np.argmax(np.abs(d)))
    if np.allclose(np.abs(d), np.eye(3)[axis], atol=1e-9):
        return f"{'+' if d[axis] > 0 else '-'}{'XYZ'[axis]}"
    return "(" + ", ".join(f"{round(float(v), 2) + 0.0:.2f}" for v in d) + ")"  # + 0.0: no "-0.00"


def up_line(up: UpEstimate) -> str:
    """The output line: ``up: +Z (format convention)``, ``up: (0.02, -0.01, 1.00), estimated from the floor plane``."""
    if up.source in ("format", "option"):
        return f"up: {up_text(up.direction)} ({up.detail})"
    return f"up: {up_text(up.direction)}, {up.detail}"


def cameras_up(poses: np.ndarray) -> np.ndarray | None:
    """(3,) unit mean of the cameras' up vectors (``-y`` of OpenCV axes), None when they cancel out.

    Parameters
    ----------
    poses : (n, 4, 4) float
        OpenCV camera-to-world in metres.
    """
    mean = -poses[:, :3, 1].mean(axis=0)
    norm = float(np.linalg.norm(mean))
    return mean / norm if norm > 1e-6 else None


def floor_normal(points: np.ndarray, centres: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, int] | None:
    """The unit normal (facing ``up``) of the floor among ``points``, and its number of points.

    RANSAC over :data:`FLOOR_HYPOTHESES` planes through three random points of the lowest
    :data:`FLOOR_DRAW_SHARE` along ``up``, scored against every point at once (hypotheses x
    points distances, no loop over points); a plane counts when its normal is
    within :data:`FLOOR_MAX_TILT_DEG` of ``up`` and it lies below every camera centre. The
    plane with most points within :data:`FLOOR_TOLERANCE_M` is refitted to them by least squares.

    Parameters
    ----------
    points : (m, 3) float
        Depth points in metres.
    centres : (n, 3) float
        Camera centres in metres.
    up : (3,) float
        The cameras' mean up (unit).

    Returns
    -------
    ((3,) float64, int) or None
        None when no plane holds :data:`FLOOR_MIN_SHARE` of the points.
    """
    rng = np.random.default_rng(FLOOR_SEED)
    if len(points) > FLOOR_POINTS:
        points = points[rng.choice(len(points), FLOOR_POINTS, replace=False)]
    m = len(points)
    need = max(3, math.ceil(FLOOR_MIN_SHARE * m))
    if m < 3:
        return None
    low = np.argsort(points @ up)[: max(3, math.ceil(FLOOR_DRAW_SHARE * m))]
    a, b, c = (points[low[i]] for i in rng.integers(0, len(low), size=(3, FLOOR_HYPOTHESES)))
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    normals = normals / np.maximum(norm, 1e-300)[:, None]
    normals *= np.where(normals @ up < 0, -1.0, 1.0)[:, None]
    offsets = np.einsum("ij,ij->i", normals, a)
    below = offsets < (centres @ normals.T).min(axis=0)
    ok = (norm > 1e-12) & (normals @ up >= math.cos(math.radians(FLOOR_MAX_TILT_DEG))) & below
    if not ok.any():
        return None
    normals, offsets = normals[ok], offsets[ok]
    # Scored in chunks of hypotheses: (points x 64) distances at a time.
    counts = np.concatenate([
        (np.abs(points @ normals[k:k + 64].T - offsets[k:k + 64]) < FLOOR_TOLERANCE_M).sum(axis=0)
        for k in range(0, len(normals), 64)
    ])
    best = int(np.argmax(counts))
    if counts[best] < need:
        return None
    on = np.abs(points @ normals[best] - offsets[best]) < FLOOR_TOLERANCE_M
    inliers = points[on]
    # The least-squares normal: the direction of least spread of the inliers.
    normal = np.linalg.svd(inliers - inliers.mean(axis=0), full_matrices=False)[2][-1]
    normal = normal if normal @ up >= 0 else -normal
    return normal, int(on.sum())


def estimate_up(capture: Capture, points: np.ndarray | None = None) -> UpEstimate:
    """The up direction of ``capture``'s metric world: its format's convention, else estimated.

    Parameters
    ----------
    capture : Capture
    points : (m, 3) float, optional
        Depth points in metres (:func:`regnf.captures.survey.depth_cloud`); None: the depth
        of at most :data:`~regnf.captures.survey.SURVEY_FRAMES` frames is read when the format
        gives no up.

    Raises
    ------
    CaptureError
        An unreadable or invalid depth file.
    """
    if capture.up is not None:
        d = np.asarray(capture.up, dtype=np.float64)
        return UpEstimate(d / np.linalg.norm(d), "format", "format convention")
    poses = metric_poses(capture)
    mean_up = cameras_up(poses)
    if mean_up is None:
        return UpEstimate(np.array([0.0, 0.0, 1.0]), "cameras",
                          "assumed: the cameras' up vectors cancel out and no floor can be told")
    if points is None:
        points = depth_cloud(capture, survey_frames(capture), poses)
    floor = floor_normal(points, poses[:, :3, 3], mean_up)
    if floor is not None:
        return UpEstimate(floor[0], "floor", "estimated from the floor plane")
    return UpEstimate(mean_up, "cameras", "estimated from the cameras' mean up vector (no floor plane found)")


def resolve_up(capture: Capture, value: str = "auto", points: np.ndarray | None = None) -> UpEstimate:
    """``--up value`` for ``capture``: the named axis, or :func:`estimate_up` (given ``points``) for ``auto``.

    Raises
    ------
    ValueError
        A value not in :data:`UP_CHOICES`.
    CaptureError
        See :func:`estimate_up`.
    """
    given = parse_up(value)
    if given is not None:
        return UpEstimate(given, "option", "given by --up")
    return estimate_up(capture, points)
