"""The room from above: what discovery found (and, where known, the true boxes), as a PNG."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from regnf.core.atomic_io import atomic_path
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.discovery import DiscoveryResult

MAX_POINTS = 30_000
"""Surface points drawn at most (a random, seeded subset: the picture, not the data)."""


def footprint(box: OrientedBox) -> np.ndarray:
    """(5, 2) float: the closed outline of an upright box seen from above (x, y)."""
    sx, sy = box.half_extents[0], box.half_extents[1]
    local = np.array([[-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0], [-sx, -sy, 0]], dtype=np.float64)
    return (local @ np.asarray(box.rotation).T + box.center)[:, :2]


def draw_top_view(result: DiscoveryResult, path: str | os.PathLike,
                  truth: Sequence[tuple[str, OrientedBox]] = (), title: str = "") -> Path:
    """Write the top view of a discovery to ``path`` (PNG, written atomically).

    Parameters
    ----------
    result : DiscoveryResult
        Its candidates' surface points are drawn grey; each identified candidate's box green
        with the library object and confidence, each unmatched (or skipped) one red and dashed.
    path : str or PathLike
    truth : sequence of (name, OrientedBox)
        True boxes in scene metres, drawn black and dotted with their names (benchmarks).
    title : str

    Returns
    -------
    Path
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 6.4), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    points = [d.candidate.points for d in result.discoveries]
    if points:
        cloud = np.concatenate(points)
        if len(cloud) > MAX_POINTS:
            cloud = cloud[np.random.default_rng(0).choice(len(cloud), MAX_POINTS, replace=False)]
        ax.scatter(cloud[:, 0], cloud[:, 1], s=0.3, c="0.6", linewidths=0, rasterized=True)
    for name, box in truth:
        xy = footprint(box)
        ax.plot(xy[:, 0], xy[:, 1], color="black", linestyle=":", linewidth=1.2)
        ax.annotate(name, xy[2], fontsize=7, color="black", xytext=(2, 2), textcoords="offset points")
    for d in result.discoveries:
        xy = footprint(d.candidate.box)
        if d.chosen is None:
            ax.plot(xy[:, 0], xy[:, 1], color="tab:red", linestyle="--", linewidth=1.2)
            ax.annotate("unmatched" if d.skipped is None else "skipped", xy[0], fontsize=7, color="tab:red", xytext=(2, -9), textcoords="offset points")
        else:
            ax.plot(xy[:, 0], xy[:, 1], color="tab:green", linewidth=1.6)
            ax.annotate(f"{d.chosen.library_name} {d.chosen.result.confidence:.2f}", xy[0], fontsize=7,
                        color="tab:green", xytext=(2, -9), textcoords="offset points")
    ax.set_aspect("equal")
    ax.margins(0.12)  # room for the labels at the edges
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    legend = "green: identified, red dashed: unmatched" + (", black dotted: true boxes" if truth else "")
    ax.set_title(f"{title}\n{legend}" if title else legend, fontsize=9)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    return path
