"""Starts for objects that stand upright: a sweep over the rotation about the up axis.

Furniture stands on the floor the way its library model does: the scene -> library rotation
maps the scene's up onto the library's up, and only the turn about it (the yaw) is unknown.
FPFH + RANSAC searches all of SO(3) from local features, and on an object seen from one side
it can find no start near the true pose at all
(docs/decisions/registration-initialisation.md). A sweep of evenly spaced yaws does not depend
on features: one of them is always within half the spacing of the truth, inside ICP's basin.

Each start: the library's up axis aligned with the scene's, the yaw, the scale from the ratio
of the two clouds' vertical extents (an object seen from one side still shows its top and its
base), the bases at the same height and the proposal box's centre on the library object's
centre. :func:`regnf.registration.initialisation.initial_hypotheses` refines each start with ICP.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .transform import SimilarityTransform


class UprightPrior(NamedTuple):
    """What the yaw sweep needs to know about the two frames."""

    scene_up: np.ndarray
    """(3,) unit up axis in the scene field frame."""
    library_up: np.ndarray
    """(3,) unit up axis in the library field frame (its canonical +Z)."""
    centre: np.ndarray
    """(3,) centre of the proposal box, scene field frame."""


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis perpendicular to a
        p = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        axis = np.cross(a, p)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about unit ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def robust_range(values: np.ndarray, tail: float) -> tuple[float, float]:
    """The ``tail`` and ``1 - tail`` quantiles of ``values`` (n,): an extent that a few stray
    samples do not stretch."""
    lo, hi = np.quantile(values, [tail, 1.0 - tail])
    return float(lo), float(hi)


def yaw_starts(
    scene_points: np.ndarray,
    library_points: np.ndarray,
    prior: UprightPrior,
    n_yaws: int,
    period: float = 2.0 * np.pi,
    tail: float = 0.005,
) -> list[SimilarityTransform]:
    """Upright scene -> library starts, evenly spaced in yaw (see the module).

    Parameters
    ----------
    scene_points : (n, 3) float
        Scene samples inside the proposal, scene field frame.
    library_points : (m, 3) float
        Samples of the whole library object, library field frame.
    prior : UprightPrior
    n_yaws : int
        Yaws to a whole turn: the starts are at ``2 pi k / n_yaws``.
    period : float
        Only the yaws in ``[0, period)`` start (at least yaw 0): the turn after which the
        object looks the same again (``2 pi / k`` for a k-fold symmetry about the up axis,
        0 for a continuous one), since the other yaws would start the same poses again.
    tail : float
        Quantile cut off each end of the vertical extents.

    Returns
    -------
    list of SimilarityTransform
        Scene field frame -> library field frame.
    """
    Ps = np.asarray(scene_points, dtype=np.float64)
    Pl = np.asarray(library_points, dtype=np.float64)
    us = np.asarray(prior.scene_up, dtype=np.float64) / np.linalg.norm(prior.scene_up)
    ul = np.asarray(prior.library_up, dtype=np.float64) / np.linalg.norm(prior.library_up)
    s_lo, s_hi = robust_range(Ps @ us, tail)
    l_lo, l_hi = robust_range(Pl @ ul, tail)
    if not (s_hi > s_lo and l_hi > l_lo):
        return []
    s = (l_hi - l_lo) / (s_hi - s_lo)
    # The library object's centre: the middle of its extent along each library axis, taken
    # across the up axis only (heights are matched at the base).
    l_mid = 0.5 * (Pl.min(axis=0) + Pl.max(axis=0))
    l_mid_flat = l_mid - (l_mid @ ul) * ul
    c_flat = prior.centre - (prior.centre @ us) * us
    align = rotation_between(us, ul)
    out = []
    yaws = 2.0 * np.pi * np.arange(n_yaws) / n_yaws
    yaws = yaws[(yaws < period - 1e-9) | (np.arange(n_yaws) == 0)]
    for yaw in yaws:  # a couple of dozen starts at most
        R = axis_rotation(ul, float(yaw)) @ align
        # Across: the box centre onto the library centre; along up: the bases level.
        t = l_mid_flat - s * (R @ c_flat) + (l_lo - s * s_lo) * ul
        out.append(SimilarityTransform(R, t, float(s)))
    return out
