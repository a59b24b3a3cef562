"""Whether a capture shows a scene seen from inside (a room) or an object seen from outside.

What ``regnf train --preset auto`` trains it as. regnf's own captures say so in their metadata
(``regnf.kind``: ``scene`` for rooms, ``object`` for library objects); for any other capture
the cameras tell: inside the box of the observed depth points, they look out at a room; outside
it, they look in at something.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np

from regnf.captures.metric import DEPTH_PERCENTILES
from regnf.captures.model import Capture

INSIDE_SHARE = 0.5
"""A capture is a scene when more than this share of its camera centres lie inside the box of its depth points."""


class SceneKind(NamedTuple):
    """What a capture shows, and why that was decided."""

    kind: Literal["scene", "object"]
    """``scene`` (seen from inside) or ``object`` (seen from outside)."""
    reason: str
    """Why, in words, for the command's output."""


def scene_kind(capture: Capture, centres: np.ndarray, points: np.ndarray) -> SceneKind:
    """Scene or object: the capture's ``regnf.kind``, else where its cameras stand.

    Parameters
    ----------
    capture : Capture
    centres : (n, 3) float
        Camera centres in metres (:func:`regnf.captures.survey.metric_poses`).
    points : (m, 3) float
        Depth points in metres (:func:`regnf.captures.survey.depth_cloud`); the box is their
        per-axis :data:`~regnf.captures.metric.DEPTH_PERCENTILES`, so a few flying pixels do
        not move it.
    """
    kind = capture.meta.get("kind")
    if kind in ("scene", "object"):
        what = "a room" if kind == "scene" else "an object"
        return SceneKind(kind, f"{what}: the capture's metadata says kind {kind!r}")
    if len(points) == 0:
        return SceneKind("object", "no depth point to tell inside from outside; object assumed")
    lo, hi = np.percentile(points, DEPTH_PERCENTILES, axis=0)
    inside = int(np.all((centres >= lo) & (centres <= hi), axis=1).sum())
    count = f"{inside} of {len(centres)} camera centres inside the box of the depth points"
    if inside > INSIDE_SHARE * len(centres):
        return SceneKind("scene", f"cameras inside the observed space: {count}")
    return SceneKind("object", f"cameras outside the observed space, looking in: {count}")
