"""Removal regions: the parts of the scene field a composite cuts away.

A region is a solid described by an SDF ``M`` in scene field units (negative inside); the
composite masks the scene with ``max(S_scene, -M)``, which removes the scene's matter
inside the region and leaves it untouched where ``M > |S_scene|``. Two shapes:

- :class:`OrientedBoxRegion`: the replaced instance's oriented box;
- :class:`ShellRegion`: the registered library surface dilated by a margin, which removes
  the object but not the wall or table it stands against.

Both can spare the floor: with ``keep_floor = z_f`` (the scene-frame height of the floor
plane, +Z up) the region is intersected with the half-space ``z >= z_f + floor_margin``,
so the floor surface and a thin layer above it survive. An intersection's SDF is the max of
the SDFs: exact inside, a lower bound outside, which is all a sphere tracer needs.
"""

from __future__ import annotations

import abc
from typing import NamedTuple

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.fields.oriented_box import ArrayLike, OrientedBox, OrientedBoxes

from .placement import Placement

DEFAULT_FLOOR_MARGIN = 0.01
"""Height above the floor plane (scene field units) below which nothing is removed."""


class RegionSample(NamedTuple):
    """A region's SDF with its cost."""

    sdf: torch.Tensor
    """(n,) float: the region's SDF M in scene field units (negative inside)."""
    evals: torch.Tensor
    """(n,) int64: field evaluations spent per point (0 for an analytic shape)."""


def _check_floor(keep_floor: float | None, floor_margin: float) -> None:
    if keep_floor is not None and not np.isfinite(keep_floor):
        raise RegnfError(f"keep_floor must be a finite height or None, got {keep_floor}")
    if not (np.isfinite(floor_margin) and floor_margin >= 0):
        raise RegnfError(f"floor_margin must be finite and >= 0, got {floor_margin}")


class RemovalRegion(torch.nn.Module, metaclass=abc.ABCMeta):
    """Base class: a solid in the scene field frame, optionally sparing the floor.

    Parameters
    ----------
    keep_floor : float, optional
        Scene-frame z of the floor plane; None removes everything inside the shape.
    floor_margin : float
        Scene units above ``keep_floor`` that are never removed, >= 0.
    """

    def __init__(self, keep_floor: float | None, floor_margin: float) -> None:
        super().__init__()
        _check_floor(keep_floor, floor_margin)
        self.keep_floor = None if keep_floor is None else float(keep_floor)
        self.floor_margin = float(floor_margin)

    @abc.abstractmethod
    def shape_sdf(self, x: torch.Tensor) -> RegionSample:
        """SDF of the region's shape before the floor cut, for points ``x`` (n, 3)."""
        ...

    @property
    def cut_height(self) -> float:
        """Scene-frame z below which nothing is removed: the floor plus its margin (-inf: no cut).
        The cut is the half-space z >= cut_height, of SDF ``cut_height - z``, intersected by max."""
        return -np.inf if self.keep_floor is None else self.keep_floor + self.floor_margin

    def evaluate(self, x: torch.Tensor) -> RegionSample:
        """The region's SDF M (n,) in scene units, floor cut included, with its cost."""
        sample = self.shape_sdf(x)
        if self.keep_floor is None:
            return sample
        above = self.cut_height - x[:, 2]
        return RegionSample(torch.maximum(sample.sdf, above.to(sample.sdf.dtype)), sample.evals)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """The region's SDF M (n,) in scene field units at points ``x`` (n, 3)."""
        return self.evaluate(x).sdf


class OrientedBoxRegion(RemovalRegion):
    """Remove everything inside an oriented box (optionally above the floor).

    Parameters
    ----------
    center : (3,) float
        Scene field frame.
    half_extents : (3,) float
        All > 0, along the box axes.
    rotation : (3, 3) float, optional
        Columns are the box axes in the scene field frame; identity by default.
    keep_floor : float, optional
        Scene-frame z of the floor plane to spare (see the module).
    floor_margin : float
        >= 0.
    """

    def __init__(
        self,
        center: ArrayLike,
        half_extents: ArrayLike,
        rotation: ArrayLike | None = None,
        keep_floor: float | None = None,
        floor_margin: float = DEFAULT_FLOOR_MARGIN,
    ) -> None:
        super().__init__(keep_floor, floor_margin)
        self.box = OrientedBox(center, half_extents, rotation)

    def shape_sdf(self, x: torch.Tensor) -> RegionSample:
        return RegionSample(
            self.box.sdf(x), torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        )


class BoxRegionUnion(torch.nn.Module):
    """The union of :class:`OrientedBoxRegion` s, ``M = min_k M_k``, evaluated at once
    (:class:`~regnf.fields.oriented_box.OrientedBoxes`); the same values as the regions
    one by one, to float rounding.

    Parameters
    ----------
    regions : sequence of OrientedBoxRegion
        At least one.
    """

    def __init__(self, regions: list[OrientedBoxRegion]) -> None:
        super().__init__()
        self.boxes = OrientedBoxes([r.box for r in regions])
        # Each region's floor cut (RemovalRegion.cut_height; -inf cuts nothing).
        floors = [r.cut_height for r in regions]
        self.register_buffer("floors", torch.tensor(floors, dtype=torch.float64), persistent=False)

    def evaluate(self, x: torch.Tensor) -> RegionSample:
        """The union's SDF M (n,) in scene units at ``x`` (n, 3); no field is evaluated."""
        m = torch.maximum(self.boxes.sdf(x), self.floors.to(x.dtype)[:, None] - x[:, 2])
        return RegionSample(m.min(dim=0).values, torch.zeros(x.shape[0], dtype=torch.long, device=x.device))


class ShellRegion(RemovalRegion):
    """Remove a dilated library surface: ``M(x) = s S_lib(T^-1 x) - dilation``.

    The library field is culled to its box grown by ``dilation + cull_pad``; outside, ``M``
    is bounded below by ``box distance - dilation >= cull_pad > 0``, which keeps the sign of
    ``max(S_scene, -M)`` and never overstates its magnitude.

    Parameters
    ----------
    field : Field
        The library field, in its own frame.
    library_to_scene : (4, 4) float
        Similarity: library field frame -> scene field frame.
    dilation : float
        Scene field units, >= 0.
    keep_floor, floor_margin
        As for :class:`OrientedBoxRegion`.
    cull : bool
        False evaluates the library field everywhere.
    cull_pad : float
        Culling margin beyond the dilation, scene units, > 0.
    """

    def __init__(
        self,
        field: Field,
        library_to_scene: ArrayLike,
        dilation: float,
        keep_floor: float | None = None,
        floor_margin: float = DEFAULT_FLOOR_MARGIN,
        cull: bool = True,
        cull_pad: float = 0.02,
    ) -> None:
        super().__init__(keep_floor, floor_margin)
        if not (np.isfinite(dilation) and dilation >= 0):
            raise RegnfError(f"dilation must be finite and >= 0, got {dilation}")
        if not (np.isfinite(cull_pad) and cull_pad > 0):
            raise RegnfError(f"cull_pad must be finite and > 0, got {cull_pad}")
        self.dilation = float(dilation)
        self.placement = Placement(field, library_to_scene, pad=self.dilation + cull_pad, cull=cull)

    def shape_sdf(self, x: torch.Tensor) -> RegionSample:
        sample = self.placement.evaluate(x)
        return RegionSample(sample.sdf - self.dilation, sample.evals)
