"""The normalised frame of a metric capture that states no scene box: from cameras and depth.

A capture in metres (nerfstudio, a phone scan) gives no bounds; they are the axis-aligned box
of its camera centres and of robust percentiles of its back-projected depth (a few flying
pixels do not blow the box up; a wall seen by a whole frame is far above the 1 % cut, so the
scene is never cropped), then :func:`regnf.captures.model.normalisation` with the rooms' margin
(:func:`normalise_metric_frames`). Every metric reader also checks each frame's depth unit here
(:func:`check_median_depth`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from regnf.captures.distortion import Distortion, normalised, pixels_to_rays
from regnf.captures.model import CaptureError, CaptureFrame, far_plane, normalisation

SCENE_MARGIN = 1.02
"""Multiplier on half the largest extent of a scene's bounds (rooms, metric captures)."""

DEPTH_PERCENTILES = (1.0, 99.0)
"""Percentiles (per axis) of the back-projected depth points that bound a metric capture."""

POINTS_PER_FRAME = 4096
"""About how many depth pixels per frame are back-projected for the bounds."""

MAX_MEDIAN_DEPTH_M = 50.0
"""Largest median valid depth of a frame, in metres, accepted as a sensor's (a unit check)."""

NEAR = 0.05
"""Near plane of the scene box, in normalised units (as the sdfstudio writer's default)."""


def check_median_depth(depth_m: np.ndarray, where: str, unit_note: str) -> None:
    """Refuse a frame whose median valid depth is beyond :data:`MAX_MEDIAN_DEPTH_M` (a wrong unit).

    Parameters
    ----------
    depth_m : (H, W) float
        The frame's depth read in metres, 0 = no depth.
    where : str
        The depth file and frame, for the message (``"<path>: frame 3"``).
    unit_note : str
        What the unit was taken to be and what to check, ending the message.

    Raises
    ------
    CaptureError
        ``"<where>: median depth <m> m is beyond 50 m <unit_note>"``.
    """
    valid = depth_m[depth_m > 0]
    median = float(np.median(valid)) if valid.size else 0.0
    if median > MAX_MEDIAN_DEPTH_M:
        raise CaptureError(f"{where}: median depth {median:.4g} m is beyond {MAX_MEDIAN_DEPTH_M:g} m {unit_note}")


def depth_points(depth: np.ndarray, K: np.ndarray, camtoworld: np.ndarray,
                 distortion: Distortion | None = None) -> np.ndarray:
    """World points of a subsample of a frame's valid depth pixels.

    Parameters
    ----------
    depth : (H, W) float
        Z-depth in metres, 0 = no depth.
    K : (3, 3) float
        Pinhole intrinsics; pixel centres at ``(u + 0.5, v + 0.5)``.
    camtoworld : (4, 4) float
        OpenCV camera-to-world in metres.
    distortion : Distortion, optional
        The frame's lens distortion (pixels through it to their rays); None: an ideal pinhole.

    Returns
    -------
    (m, 3) float64
        Points in metres, one per kept pixel with depth > 0 (and a ray).
    """
    h, w = depth.shape
    step = max(1, int(np.sqrt(h * w / POINTS_PER_FRAME)))
    v, u = np.mgrid[0:h:step, 0:w:step]
    z = depth[v, u].astype(np.float64)
    keep = z > 0
    u, v, z = u[keep] + 0.5, v[keep] + 0.5, z[keep]
    uv = np.stack([u, v], -1)
    # Inverse of the pinhole projection (skew included), then of the lens.
    xy = normalised(uv, K) if distortion is None else pixels_to_rays(uv, K, distortion)
    ray = np.isfinite(xy).all(-1)
    x, y, z = xy[ray, 0], xy[ray, 1], z[ray]
    cam = np.stack([x * z, y * z, z], axis=1)
    return cam @ camtoworld[:3, :3].T + camtoworld[:3, 3]


def metric_bounds(centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(2, 3) box of the camera centres and of the depth points' :data:`DEPTH_PERCENTILES`.

    Parameters
    ----------
    centres : (n, 3) float
        Camera centres in metres.
    points : (m, 3) float
        Back-projected depth points in metres (may be empty).

    Returns
    -------
    (2, 3) float64
        Min and max corner in metres.
    """
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    if len(points):
        plo, phi = np.percentile(points, DEPTH_PERCENTILES, axis=0)
        lo, hi = np.minimum(lo, plo), np.maximum(hi, phi)
    return np.stack([lo, hi]).astype(np.float64)


def normalise_metric_frames(frames: Sequence[CaptureFrame], points: np.ndarray) -> tuple[np.ndarray, dict]:
    """Move frames posed in metres into the normalised frame of their bounds (:func:`metric_bounds`).

    Parameters
    ----------
    frames : sequence of CaptureFrame
        On entry ``camtoworld`` is in metres and ``depth_scale`` is metres per file unit; on
        return both are in normalised units (poses are only moved and scaled: the world does
        not turn).
    points : (m, 3) float
        Back-projected depth points in metres (:func:`depth_points`).

    Returns
    -------
    (4, 4) float64
        ``worldtogt``, normalised -> metres, with the rooms' margin :data:`SCENE_MARGIN`.
    dict
        The scene box: ``aabb`` the unit box, ``near`` :data:`NEAR`, ``far`` from the cameras.
    """
    centres = np.stack([fr.camtoworld[:3, 3] for fr in frames])
    worldtogt = normalisation(metric_bounds(centres, points), SCENE_MARGIN)
    s, c = float(worldtogt[0, 0]), worldtogt[:3, 3]
    for fr in frames:
        fr.camtoworld = fr.camtoworld.copy()
        fr.camtoworld[:3, 3] = (fr.camtoworld[:3, 3] - c) / s
        fr.depth_scale = fr.depth_scale / s
    scene_box = {"aabb": np.array([[-1.0] * 3, [1.0] * 3]), "near": NEAR, "far": far_plane((centres - c) / s)}
    return worldtogt, scene_box
