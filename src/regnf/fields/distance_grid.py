"""A coarse grid of SDF samples that bounds the distance to the surface (empty-space skipping).

The field is sampled once at the centres ``c`` of a ``res^3`` grid over its bounds. If the
field is ``L``-Lipschitz and ``f(c) > 0``, no surface lies within ``f(c) / L`` of ``c``,
so from any point ``p`` of that cell the surface is at least

    lb(p) = f(c) / L - |p - c|

away. A sphere tracer may step ``lb(p)`` along any ray from ``p`` for the price of a table
look-up instead of a field evaluation. Exact SDFs (analytic fields, and composites, whose
culling stand-ins are 1-Lipschitz too) have ``L = 1``; a neural field that overestimates
its distance needs ``L > 1`` to stay safe.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import DEFAULT_CHUNK, Field


class DistanceGrid(NamedTuple):
    """Cell-centre SDF samples of a field over its bounds, in the field frame."""

    lo: torch.Tensor
    """(3,) float: the grid's lower corner (the field's ``bounds[0]``)."""
    cell: torch.Tensor
    """(3,) float: cell size along each axis."""
    values: torch.Tensor
    """(res, res, res) float: the SDF at the cell centres, indexed [i_x, i_y, i_z]."""
    lipschitz: float
    """Lipschitz constant assumed for the field, >= 1 for a distance."""
    build_evals: int
    """Field evaluations spent building the grid (composite costs included)."""

    @property
    def resolution(self) -> int:
        return int(self.values.shape[0])

    @staticmethod
    @torch.no_grad()
    def build(
        field: Field, resolution: int = 32, lipschitz: float = 1.0, chunk: int = DEFAULT_CHUNK
    ) -> DistanceGrid:
        """Sample ``field`` at the ``resolution^3`` cell centres of its bounds.

        Raises ``ValueError`` for a resolution < 1, a Lipschitz constant that is not finite and
        > 0, or a field that returns non-finite values.
        """
        if int(resolution) != resolution or resolution < 1:
            raise RegnfError(f"grid resolution must be an integer >= 1, got {resolution}")
        if not (math.isfinite(lipschitz) and lipschitz > 0):
            raise RegnfError(f"lipschitz must be finite and > 0, got {lipschitz}")
        lo, hi = field.bounds[0], field.bounds[1]
        cell = (hi - lo) / resolution
        ticks = torch.arange(resolution, device=field.device, dtype=lo.dtype) + 0.5
        gx, gy, gz = torch.meshgrid(ticks, ticks, ticks, indexing="ij")
        centres = lo + torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3) * cell
        values, evals = [], 0
        for i in range(0, centres.shape[0], chunk):  # a loop over chunks bounds memory
            s = field.evaluate(centres[i : i + chunk])
            values.append(s.sdf.to(lo.dtype))
            evals += int(s.evals.sum())
        v = torch.cat(values)
        if not bool(torch.isfinite(v).all()):
            raise RegnfError(
                f"field {field.name or type(field).__name__!r} returned non-finite SDF values at "
                f"{int((~torch.isfinite(v)).sum())} of {v.numel()} grid points"
            )
        r = int(resolution)
        return DistanceGrid(lo.clone(), cell, v.reshape(r, r, r), float(lipschitz), evals)

    def lower_bound(self, p: torch.Tensor) -> torch.Tensor:
        """Safe distance (n,) to the surface from points ``p`` (n, 3) of the field frame.

        ``-inf`` where nothing is known: outside the grid or in a cell whose centre is inside
        matter (or where the bound is not positive).
        """
        r = self.resolution
        f = (p - self.lo.to(p.dtype)) / self.cell.to(p.dtype)
        ijk = f.floor().long()
        inside = ((ijk >= 0) & (ijk < r)).all(dim=-1)
        ijk = ijk.clamp(0, r - 1)
        v = self.values[ijk[:, 0], ijk[:, 1], ijk[:, 2]].to(p.dtype)
        centre = self.lo.to(p.dtype) + (ijk.to(p.dtype) + 0.5) * self.cell.to(p.dtype)
        lb = v / self.lipschitz - torch.linalg.vector_norm(p - centre, dim=-1)
        ok = inside & (v > 0) & (lb > 0)
        return torch.where(ok, lb, torch.full_like(lb, -math.inf))
