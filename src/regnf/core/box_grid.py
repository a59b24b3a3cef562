"""Cubic cells over an axis-aligned box: how many along each axis."""

from __future__ import annotations

import math

import torch


def grid_shape(resolution: int, extent: torch.Tensor) -> tuple[int, int, int]:
    """Cells per axis (x, y, z) for a box of ``extent`` (3,) with ``resolution`` on its longest axis.

    Anisotropic boxes (a room is wide and low) get proportionally fewer cells on short axes,
    so the cells stay cubic and no memory is spent on empty height.
    """
    rel = (extent / extent.max()).tolist()
    return tuple(max(2, math.ceil(resolution * r)) for r in rel)  # type: ignore[return-value]
