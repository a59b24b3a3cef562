"""A library field placed in the scene, queried only where it can matter (culling).

A library field lives in its own field frame. ``library_to_scene`` is the similarity
``T(y) = s R y + t`` from that frame to the SCENE FIELD frame, so a scene point ``x`` is
``T^-1 x`` in the library frame and, because an SDF scales with its geometry, the distance
in scene units is ``s * S_lib(T^-1 x)`` (``s`` > 1 makes the object, and its distances,
bigger in the scene).

Culling: the library surface lies inside the library field's bounds (the Field contract),
whose image under ``T`` is an oriented box. Outside that box (grown by ``pad``) the distance to the box is a
lower bound of the distance to the object and has the same (positive) sign, so it stands in
for the field there and the field is evaluated only inside the padded box. Because the
stand-in is >= ``pad`` wherever it is used, every point closer than ``pad`` to the
object's surface is evaluated exactly: a tracer whose hit tolerance is below ``pad`` never
stops on the stand-in.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.analytic import Transformed
from regnf.fields.field import Field
from regnf.fields.oriented_box import ArrayLike, OrientedBox, as_float64


class PlacedObject(NamedTuple):
    """A library object to add to a composite."""

    field: Field
    """The library field, in its own field frame."""
    library_to_scene: ArrayLike
    """(4, 4) float64 similarity: library FIELD frame -> scene FIELD frame."""
    instance_id: int
    """>= 1, unique within a composite; 0 is the scene and -1 the background."""
    tint: tuple[float, float, float] | None = None
    """RGB in [0, 1] multiplied into the object's colour, or None for its own colour."""


class CulledSample(NamedTuple):
    """A placed field's distances with their cost."""

    sdf: torch.Tensor
    """(n,) float: exact within the padded box, the box distance (a lower bound) outside."""
    evals: torch.Tensor
    """(n,) int64: 1 where the library field was evaluated, else 0."""


class Placement(torch.nn.Module):
    """A field mapped by a similarity into an outer frame, culled to its oriented box.

    Parameters
    ----------
    field : Field
        Library field, in its own frame.
    to_outer : (4, 4) float
        Similarity: the field's frame -> the outer (scene field) frame.
    pad : float
        Culling margin in outer-frame units, > 0.
    cull : bool
        False evaluates the field at every point (for reference and tests).
    """

    def __init__(self, field: Field, to_outer: ArrayLike, pad: float, cull: bool = True) -> None:
        super().__init__()
        if not isinstance(field, Field):
            raise TypeError(f"a placed object needs a Field, got {type(field).__name__}")
        if not (np.isfinite(pad) and pad > 0):
            raise RegnfError(f"the culling pad must be finite and > 0, got {pad}")
        M = as_float64(to_outer, (4, 4), "library_to_scene")
        # Transformed owns the frame change and the scale direction: s * S(T^-1 x).
        self.mapped = Transformed(field, M)
        self.box = OrientedBox.from_bounds(field.bounds, M)
        self.pad, self.cull = float(pad), bool(cull)
        self.to(field.device)

    @property
    def field(self) -> Field:
        return self.mapped.child

    @property
    def scale(self) -> float:
        """The uniform scale ``s`` of library -> outer."""
        return float(self.mapped.scale)

    def aabb(self) -> torch.Tensor:
        """(2, 3) float64 outer-frame AABB of the object's box (CPU)."""
        return self.box.aabb()

    def evaluate(self, x: torch.Tensor, box_distance: torch.Tensor | None = None) -> CulledSample:
        """Distances (n,) in outer units of points ``x`` (n, 3), culled (see the module).

        ``box_distance`` (n,): the signed distance of ``x`` to :attr:`box` when the caller has
        it already (a composite computes every placement's at once); computed here if None.
        """
        n = x.shape[0]
        if not self.cull:
            return CulledSample(
                self.mapped.sdf(x), torch.ones(n, dtype=torch.long, device=x.device)
            )
        bound = self.box.sdf(x) if box_distance is None else box_distance
        near = bound <= self.pad
        idx = near.nonzero().squeeze(1)
        if idx.numel() > 0:
            # Out-of-place index_put keeps autograd through both the exact values and the bound.
            bound = bound.index_put((idx,), self.mapped.sdf(x[idx]).to(bound.dtype))
        return CulledSample(bound, near.long())

    def color(self, x: torch.Tensor, d: torch.Tensor | None) -> torch.Tensor:
        """The library colour (n, 3) at ``x`` (n, 3), directions rotated into its frame."""
        return self.mapped.color(x, d)
