"""What every renderer does around its ray marching: camera sanity and shading of hits."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import Field


def world_rotation(field: Field, dtype: torch.dtype) -> torch.Tensor:
    """(3, 3) rotation part of ``field.to_world`` (its scale divided out), in ``dtype``."""
    A = field.to_world[:3, :3]
    return (A / torch.linalg.det(A).abs() ** (1.0 / 3.0)).to(dtype)


@torch.no_grad()
def check_camera_outside(field: Field, origin: torch.Tensor) -> None:
    """Raise ``ValueError`` if the camera centre ``origin`` (3,) (field frame) is inside matter.

    Only checked inside the field's bounds: outside them a field has no surface by
    definition (and a neural field's values there mean nothing).
    """
    p = origin.reshape(1, 3).to(device=field.device, dtype=field.bounds.dtype)
    if not bool(field.contains(p)[0]):
        return
    s = field.evaluate(p)
    v = float(s.sdf[0])
    if not math.isfinite(v):
        raise RegnfError(
            f"field {field.name or type(field).__name__!r} returned a non-finite SDF ({v}) at "
            f"the camera centre {p[0].tolist()} (field frame)"
        )
    if v < 0:
        who = int(s.winner[0])
        what = "the scene" if who == 0 else f"instance {who}"
        raise RegnfError(
            f"the camera centre {p[0].tolist()} (field frame) is inside matter of {what} "
            f"(sdf = {v:.4g} < 0); move the camera out of the object"
        )


class Shaded(NamedTuple):
    """Colour and normal of every ray (background where missed)."""

    rgb: torch.Tensor
    """(n, 3) float in [0, 1]."""
    normals: torch.Tensor | None
    """(n, 3) float: unit outward normals in the WORLD frame; 0 where missed. None when not asked for."""


def shade_hits(
    field: Field,
    points: torch.Tensor,
    dirs: torch.Tensor,
    hit: torch.Tensor,
    background: Sequence[float],
    chunk: int,
    normals: bool = True,
) -> Shaded:
    """Colour (view direction ``dirs``) and, with ``normals``, autograd normals at the hit
    ``points`` (n, 3)."""
    n, dtype, dev = points.shape[0], points.dtype, points.device
    rgb = torch.tensor(list(background), dtype=dtype, device=dev).expand(n, 3).clone()
    out = torch.zeros(n, 3, dtype=dtype, device=dev) if normals else None
    R = world_rotation(field, dtype)
    rows = hit.nonzero().squeeze(1)
    for i in range(0, rows.numel(), chunk):  # a loop over chunks bounds autograd memory
        r = rows[i : i + chunk]
        p, d = points[r], dirs[r]
        if out is not None:
            _, g = field.sdf_and_gradient(p)
            out[r] = torch.nn.functional.normalize(g.to(dtype), dim=-1) @ R.T
        with torch.no_grad():
            rgb[r] = field.color(p, d).to(dtype).clamp(0.0, 1.0)
    return Shaded(rgb, out)
