"""What a capture holds, in numbers: frames, image size, intrinsics, depth, extent (``regnf inspect-capture``).

Every frame's depth is read once (one frame at a time); the valid share counts every pixel,
the depth percentiles and the world extent use a subsample of each frame
(:data:`~regnf.captures.metric.POINTS_PER_FRAME` pixels, as the metric bounds do).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regnf.captures.metric import POINTS_PER_FRAME, depth_points, metric_bounds
from regnf.captures.model import Capture
from regnf.captures.survey import metric_poses

DEPTH_REPORT_PERCENTILES = (1.0, 50.0, 99.0)
"""Percentiles of the valid depth that ``regnf inspect-capture`` prints."""


@dataclass
class DepthSummary:
    """The depth of every frame of a capture, summarised."""

    percentiles: np.ndarray
    """(3,) metres at :data:`DEPTH_REPORT_PERCENTILES` of the valid depth (NaN where none)."""
    valid_share: float
    """Share of the pixels of frames with depth that have a depth (0 where no frame has one)."""
    frames_with_depth: int
    """Frames that have a depth file."""
    points: np.ndarray
    """(m, 3) float64 subsample of the back-projected depth, metres."""
    extent: np.ndarray
    """(2, 3) min and max corner of the cameras and the depth percentiles, metres (:func:`metric_bounds`)."""


def summarise_depth(capture: Capture) -> DepthSummary:
    """Read every frame's depth once and summarise it.

    Raises
    ------
    CaptureError
        An unreadable or invalid depth file (:meth:`regnf.captures.model.Capture.depth`).
    """
    poses = metric_poses(capture)
    valid_pixels = total_pixels = 0
    values, clouds = [np.zeros(0)], [np.zeros((0, 3))]
    for i, frame in enumerate(capture.frames):
        depth = capture.depth(i)
        if depth is None:
            continue
        depth_m = depth * np.float32(capture.scale)
        valid = depth_m > 0
        valid_pixels += int(valid.sum())
        total_pixels += valid.size
        step = max(1, int(np.sqrt(valid.size / POINTS_PER_FRAME)))
        sub = depth_m[::step, ::step]
        values.append(sub[sub > 0].astype(np.float64))
        clouds.append(depth_points(depth_m, frame.intrinsics, poses[i], frame.distortion))
    depths, points = np.concatenate(values), np.concatenate(clouds)
    percentiles = (np.percentile(depths, DEPTH_REPORT_PERCENTILES) if depths.size
                   else np.full(len(DEPTH_REPORT_PERCENTILES), np.nan))
    return DepthSummary(
        percentiles=np.asarray(percentiles, dtype=np.float64),
        valid_share=valid_pixels / total_pixels if total_pixels else 0.0,
        frames_with_depth=len(clouds) - 1,
        points=points,
        extent=metric_bounds(poses[:, :3, 3], points),
    )


def skipped_note(capture: Capture) -> str:
    """``, 1 skipped by the reader`` where the reader skipped frames (ScanNet's invalid poses), else ``""``."""
    skipped = capture.meta.get("skipped_frames")
    if isinstance(skipped, int) and not isinstance(skipped, bool) and skipped > 0:
        return f", {skipped} skipped by the reader"
    return ""


def frames_line(capture: Capture) -> str:
    """``12 (train 10, test 2), 1 skipped``: the frame counts, and frames the reader skipped."""
    train, test = len(capture.train_indices()), len(capture.test_indices())
    return f"{len(capture.frames)} (train {train}, test {test})" + skipped_note(capture)


def span(values: np.ndarray, digits: int = 1) -> str:
    """``20.0`` when all ``values`` are equal, else ``20.0-21.5``."""
    lo, hi = float(np.min(values)), float(np.max(values))
    return f"{lo:.{digits}f}" if np.isclose(lo, hi) else f"{lo:.{digits}f}-{hi:.{digits}f}"


def intrinsics_line(capture: Capture) -> str:
    """``fx 20.0, fy 21.0, cx 19.5, cy 15.2 px; distortion none`` (ranges where frames differ)."""
    Ks = np.stack([np.asarray(f.intrinsics, dtype=np.float64) for f in capture.frames])
    parts = [f"{name} {span(Ks[:, r, c])}" for name, r, c in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2))]
    models = sorted({f.distortion.model for f in capture.frames if f.distortion is not None})
    plain = sum(f.distortion is None for f in capture.frames)
    if not models:
        lens = "none"
    else:
        lens = ", ".join(models) + (f" ({plain} frames none)" if plain else "")
    colour = sum(f.rgb_intrinsics is not None for f in capture.frames)
    grid = f"; colour on a grid of its own in {colour} frames" if colour else ""
    return f"{', '.join(parts)} px; distortion {lens}{grid}"


def depth_line(summary: DepthSummary, frames: int) -> str:
    """``p1 1.02 m, p50 2.71 m, p99 5.80 m; valid 97.3 % of the pixels (8 of 8 frames have depth)``."""
    p = summary.percentiles
    values = ("none valid" if np.isnan(p).all()
              else ", ".join(f"p{q:g} {v:.2f} m" for q, v in zip(DEPTH_REPORT_PERCENTILES, p)))
    return (f"{values}; valid {100.0 * summary.valid_share:.1f} % of the pixels "
            f"({summary.frames_with_depth} of {frames} frames have depth)")


def extent_line(summary: DepthSummary) -> str:
    """``6.00 x 5.00 x 3.00 m, from (1.00, -2.00, 0.00) to (7.00, 3.00, 3.00)``."""
    lo, hi = summary.extent
    def text(values: np.ndarray) -> str:
        return ", ".join(f"{round(float(v), 2) + 0.0:.2f}" for v in values)  # + 0.0: no "-0.00"

    size = " x ".join(f"{v:.2f}" for v in hi - lo)
    return f"{size} m, from ({text(lo)}) to ({text(hi)})"
