"""Oriented boxes: the culling volume of a placed object and a removal region's shape.

A box is ``{c + R q : |q_k| <= h_k}`` in some outer frame (the scene field frame here):
centre ``c`` (3,), half extents ``h`` (3,) and axes ``R`` (3, 3), whose COLUMNS are the box
axes expressed in the outer frame. Its SDF is exact (Euclidean distance outside, minus the
distance to the nearest face inside), so it is 1-Lipschitz and a lower bound of the
distance to anything the box contains.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from regnf.neural_fields.analytic import box_sdf
from regnf.neural_fields.similarity import decompose_similarity
from regnf.registration.proposal import ProposalBox

ArrayLike = torch.Tensor | np.ndarray | Sequence[float] | Sequence[Sequence[float]]


def as_float64(value: ArrayLike, shape: tuple[int, ...], what: str) -> torch.Tensor:
    """``value`` as a finite CPU float64 tensor of ``shape``, or a clear ``ValueError``."""
    t = torch.as_tensor(
        value.detach().cpu() if isinstance(value, torch.Tensor) else np.asarray(value),
        dtype=torch.float64,
    )
    if tuple(t.shape) != shape:
        raise ValueError(f"{what} must have shape {shape}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{what} has non-finite entries: {t.tolist()}")
    return t.clone()


class OrientedBox(torch.nn.Module):
    """A box with its own axes, as float64 buffers (``.to(device)`` moves it): the torch form of
    :class:`regnf.registration.proposal.ProposalBox`, which validates it.

    Parameters
    ----------
    center : (3,) float
        In the outer frame.
    half_extents : (3,) float
        All > 0, along the box's own axes.
    rotation : (3, 3) float, optional
        Columns are the box axes in the outer frame (a rotation); identity by default.
    """

    center: torch.Tensor
    half_extents: torch.Tensor
    rotation: torch.Tensor

    def __init__(
        self, center: ArrayLike, half_extents: ArrayLike, rotation: ArrayLike | None = None
    ) -> None:
        super().__init__()
        # One validation of a box for the whole project: the proposal's (finite, half extents
        # > 0, a proper rotation).
        box = ProposalBox(
            as_float64(center, (3,), "box center").numpy(),
            as_float64(half_extents, (3,), "box half_extents").numpy(),
            None if rotation is None else as_float64(rotation, (3, 3), "box rotation").numpy(),
        )
        c, h, R = (torch.from_numpy(np.array(a, dtype=np.float64)) for a in box)
        self.register_buffer("center", c)
        self.register_buffer("half_extents", h)
        self.register_buffer("rotation", R)

    @staticmethod
    def from_bounds(bounds: torch.Tensor, matrix: ArrayLike) -> OrientedBox:
        """The image of the AABB ``bounds`` (2, 3) under the similarity ``matrix`` (4, 4).

        A similarity maps a box to a box: centre ``s R c + t``, half extents ``s h``, axes ``R``.
        """
        M = as_float64(matrix, (4, 4), "similarity matrix")
        R, t, s = decompose_similarity(M)
        lo, hi = bounds.detach().cpu().double()
        return OrientedBox(s * (R @ (0.5 * (lo + hi))) + t, s * 0.5 * (hi - lo), R)

    def local(self, x: torch.Tensor) -> torch.Tensor:
        """Points ``x`` (n, 3) of the outer frame in box coordinates ``R^T (x - c)`` (n, 3)."""
        return (x - self.center.to(x.dtype)) @ self.rotation.to(x.dtype)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Exact signed distance (n,) of points ``x`` (n, 3) to the box, in outer-frame units."""
        return box_sdf(self.local(x), self.half_extents.to(x.dtype))

    def aabb(self) -> torch.Tensor:
        """(2, 3) float64 axis-aligned bounds of the box in the outer frame (CPU)."""
        # The half size of a rotated box along outer axis k is sum_j |R_kj| h_j.
        half = self.rotation.detach().cpu().abs() @ self.half_extents.detach().cpu()
        c = self.center.detach().cpu()
        return torch.stack([c - half, c + half])
