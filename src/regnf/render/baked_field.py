"""A field baked once into dense grids of distance and colour, read by trilinear look-ups.

For rendering many images of the same fields (``regnf render --render.renderer baked``), every
network evaluation of the sphere tracer (about 15 per pixel) becomes a table look-up: the field's
SDF is sampled at the nodes of a regular grid over its bounds, and its colour at the nodes
within ``band_cells`` cells of its surface (a hit's trilinear cell has all its corners there).
The cell is chosen from the pixel footprint of the cameras that will look (:func:`bake_cell`): a
finer grid shows nothing more.

Outside its bounds a baked field is a lower bound of the distance to anything inside them: the
larger of the distance to the bounds and the border value less that distance. The source field
is the exact fallback: render it where a grid's resolution is not enough (the PSNR lost is
measured in ``regnf bench render``, row ``baked``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from regnf.core.errors import RegnfError
from regnf.fields.field import DEFAULT_CHUNK, Field, FieldInfo, check_points
from regnf.render.camera import Camera


@dataclass(frozen=True)
class BakeConfig:
    """How :func:`bake` samples a field."""

    cell_pixels: float = 0.5
    """Grid cell, multiples of the cameras' pixel footprint (docs/decisions/rendering-speed.md)."""
    max_nodes: int = 2**25
    """Most grid nodes of one field, 16 bytes each; a coarser cell is taken when the footprint needs more."""
    max_total_nodes: int = 2**27
    """Most grid nodes one bake makes in all; a larger bake is refused (docs/decisions/rendering-speed.md)."""
    band_cells: float = 2.0
    """Distance from the surface, cells, up to which nodes get a colour (docs/decisions/rendering-speed.md)."""

    coarse_stride: int = 4
    """Node stride of the SDF's interpolated first pass; 1: none (docs/decisions/rendering-speed.md)."""

    def __post_init__(self) -> None:
        if isinstance(self.coarse_stride, bool) or int(self.coarse_stride) != self.coarse_stride \
                or self.coarse_stride < 1:
            raise RegnfError(f"coarse_stride must be an integer >= 1, got {self.coarse_stride}")
        if not (math.isfinite(self.cell_pixels) and self.cell_pixels > 0):
            raise RegnfError(f"cell_pixels must be finite and > 0, got {self.cell_pixels}")
        for name in ("max_nodes", "max_total_nodes"):
            if getattr(self, name) < 8:
                raise RegnfError(f"{name} must be >= 8, got {getattr(self, name)}")
        if not (math.isfinite(self.band_cells) and self.band_cells >= math.sqrt(3.0)):
            raise RegnfError(f"band_cells must be >= sqrt(3) (a hit's cell corners), got {self.band_cells}")


def bake_cell(field: Field, cameras: Sequence[Camera], config: BakeConfig = BakeConfig(),
              to_world: np.ndarray | None = None) -> float:
    """The grid cell (field units) for ``field`` seen by ``cameras`` (metres).

    The pixel footprint is the median over the cameras of their distance to the centre of the
    field's bounds divided by their focal length in pixels, times ``config.cell_pixels``; no
    finer than a grid of ``config.max_nodes`` nodes over the bounds allows.

    Parameters
    ----------
    field : Field
    cameras : sequence of Camera
    config : BakeConfig
    to_world : (4, 4) float, optional
        Where the field stands: a similarity from its frame to the cameras' world (a library
        field placed in a scene); default ``field.to_world``.
    """
    if not cameras:
        raise RegnfError("bake_cell needs at least one camera")
    W = field.to_world.detach().cpu().double().numpy() if to_world is None else np.asarray(to_world, np.float64)
    if W.shape != (4, 4) or not np.isfinite(W).all():
        raise RegnfError(f"to_world must be a finite (4, 4) similarity, got shape {W.shape}")
    lo, hi = field.bounds.detach().cpu().double().numpy()
    centre = W[:3, :3] @ ((lo + hi) / 2) + W[:3, 3]
    metres_per_unit = float(abs(np.linalg.det(W[:3, :3])) ** (1.0 / 3.0))
    if not metres_per_unit > 0:
        raise RegnfError("to_world is degenerate (its scale is 0)")
    footprints = [np.linalg.norm(np.asarray(c.camera_to_world)[:3, 3] - centre) / float(c.K[0, 0]) for c in cameras]
    cell = config.cell_pixels * float(np.median(footprints)) / metres_per_unit
    cell = max(cell, (float(np.prod(hi - lo)) / config.max_nodes) ** (1.0 / 3.0), 1e-9)
    while math.prod(grid_nodes(field.bounds, cell, config.coarse_stride)) > config.max_nodes:  # the end nodes and rounding
        cell *= 1.01
    return cell


RGB_STORAGE = torch.float16
"""How a baked colour grid is kept and stored: three quarters of a grid's bytes are colour, and
half precision takes a data set's grids from 1.0 to 0.63 GB (``regnf generate``, the demo's stage)."""


def grid_nodes(bounds: torch.Tensor, cell: float, stride: int = 1) -> tuple[int, int, int]:
    """Nodes per axis (x, y, z) of a grid over ``bounds`` (2, 3) with cells of about ``cell``
    (at most that), ``stride`` cells times a whole number per axis."""
    extent = (bounds[1] - bounds[0]).detach().cpu().double()
    return tuple(stride * max(1, math.ceil(math.ceil(float(e) / cell) / stride)) + 1  # type: ignore[return-value]
                 for e in extent)


class BakedField(Field):
    """SDF and colour of a field on the nodes of a dense grid over its bounds.

    Parameters
    ----------
    sdf_grid : (nz, ny, nx) float
        Signed distance at the nodes (field units), indexed [z, y, x].
    rgb_grid : (3, nz, ny, nx) float
        Colour at the nodes (in [0, 1] within the surface band). Kept to half precision (at most
        2.4e-4 off, a sixteenth of an 8-bit level), as its file stores it
        (:func:`~regnf.render.baked_io.save_baked`): a grid read back is the grid baked.
    bounds : (2, 3) float
        The grid's corners (its first and last nodes).
    to_world : (4, 4) float
    info : FieldInfo
    """

    def __init__(self, sdf_grid: torch.Tensor, rgb_grid: torch.Tensor, bounds: torch.Tensor,
                 to_world: torch.Tensor, info: FieldInfo) -> None:
        super().__init__(bounds, to_world, info)
        if sdf_grid.ndim != 3 or rgb_grid.shape != (3, *sdf_grid.shape) or min(sdf_grid.shape) < 2:
            raise RegnfError(f"grids must be (nz, ny, nx) and (3, nz, ny, nx) with >= 2 nodes an axis, got "
                             f"{tuple(sdf_grid.shape)} and {tuple(rgb_grid.shape)}")
        self.register_buffer("sdf_grid", sdf_grid.float()[None, None].contiguous().to(self.device))
        self.register_buffer("rgb_grid", rgb_grid.to(RGB_STORAGE).float()[None].contiguous().to(self.device))

    @property
    def nodes(self) -> tuple[int, int, int]:
        """Nodes per axis (x, y, z)."""
        nz, ny, nx = self.sdf_grid.shape[2:]
        return nx, ny, nz

    def _lookup(self, grid: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """(C, n) trilinear values of ``grid`` (1, C, nz, ny, nx) at points ``x`` (n, 3)."""
        lo, hi = self.bounds[0], self.bounds[1]
        u = (x - lo) / (hi - lo) * 2.0 - 1.0  # grid_sample's [-1, 1], (x, y, z) order
        out = F.grid_sample(grid, u.to(grid.dtype).view(1, 1, 1, -1, 3), mode="bilinear",
                            padding_mode="border", align_corners=True)
        return out.view(grid.shape[1], -1)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        check_points(x, self)
        inside = torch.maximum(torch.minimum(x, self.bounds[1]), self.bounds[0])
        v = self._lookup(self.sdf_grid, x)[0]
        # Outside, every surface is inside the bounds: at least the way back into them away,
        # and at least the border value less that way (a lower bound, safe to step).
        out = torch.linalg.norm(x - inside, dim=-1)
        return torch.where(out > 0, torch.maximum(out, v - out), v)

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        check_points(x, self)
        return self._lookup(self.rgb_grid, x).T.clamp(0.0, 1.0)


def _slabs(axes: Sequence[torch.Tensor], chunk: int):
    """(first z index, number of z slabs, (m, 3) node points) of the grid on ``axes`` (x, y, z),
    a few z slabs at a time (about ``chunk`` nodes), in [z, y, x] order."""
    nx, ny = len(axes[0]), len(axes[1])
    per = max(1, chunk // (nx * ny))
    for z0 in range(0, len(axes[2]), per):
        zs = axes[2][z0:z0 + per]
        gz, gy, gx = torch.meshgrid(zs, axes[1], axes[0], indexing="ij")
        yield z0, len(zs), torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)


@torch.no_grad()
def bake(field: Field, cell: float, config: BakeConfig = BakeConfig(), chunk: int = DEFAULT_CHUNK,
         progress: bool = False) -> BakedField:
    """Sample ``field`` on a grid of cells of about ``cell`` (field units) over its bounds.

    Parameters
    ----------
    field : Field
        A field whose colour depends on the point only (a view-dependent colour is baked as
        seen along the surface normal).
    cell : float
        Cell size in field units, for example :func:`bake_cell`.
    config : BakeConfig
    chunk : int
        Points per evaluation.
    progress : bool
        Show a progress bar over the grid's z slabs.

    Returns
    -------
    BakedField
        On the field's device, with the field's ``to_world``, ``info`` and visibility grid.
    """
    if not (math.isfinite(cell) and cell > 0):
        raise RegnfError(f"cell must be finite and > 0, got {cell}")
    bounds = field.bounds.detach()
    k = config.coarse_stride
    nx, ny, nz = grid_nodes(bounds, cell, k)
    if nx * ny * nz > config.max_nodes:
        raise RegnfError(f"a grid of {nx}x{ny}x{nz} nodes exceeds max_nodes={config.max_nodes}; take a larger cell")
    dev, dt = field.device, bounds.dtype
    axes = [torch.linspace(float(bounds[0, a]), float(bounds[1, a]), n, device=dev, dtype=dt)
            for a, n in enumerate((nx, ny, nz))]
    step = float(((bounds[1] - bounds[0]) / torch.tensor([nx - 1, ny - 1, nz - 1], device=dev)).max())
    band = config.band_cells * step
    # 1. Every k-th node, then trilinear in between: exact at those nodes, and within `slack`
    # of a 1-Lipschitz distance elsewhere (the farthest a point is from its cell's corners).
    coarse_axes = [a[::k] for a in axes]
    coarse = torch.empty(len(coarse_axes[2]), len(coarse_axes[1]), len(coarse_axes[0]), device=dev)
    for z0, n, x in _slabs(coarse_axes, chunk):
        coarse[z0:z0 + n] = field.sdf_chunked(x, chunk).view(n, *coarse.shape[1:])
    sdf = F.interpolate(coarse[None, None], size=(nz, ny, nx), mode="trilinear", align_corners=True)[0, 0]
    slack = 0.5 * math.sqrt(3.0) * k * step if k > 1 else 0.0
    # 2. The field itself at every node that may lie within the band; the others keep the
    # interpolation less the slack, a lower bound of their distance (safe to step).
    rgb = torch.zeros(3, nz, ny, nx, device=dev)
    bar = tqdm(total=nz, desc=f"bake {field.name or 'field'}", unit="slab", disable=not progress)
    for z0, n, x in _slabs(axes, chunk):
        guess = sdf[z0:z0 + n].reshape(-1)
        near = guess.abs() <= band + slack
        exact = guess.abs().sub(slack).clamp_min(0.0).copysign(guess)
        if bool(near.any()):
            exact[near] = field.sdf_chunked(x[near], chunk).to(exact.dtype)
            coloured = exact.abs() <= band
            c = torch.zeros(len(x), 3, device=dev)
            if bool(coloured.any()):
                c[coloured] = field.color_chunked(x[coloured], None, chunk).float()
            rgb[:, z0:z0 + n] = c.T.reshape(3, n, ny, nx)
        sdf[z0:z0 + n] = exact.view(n, ny, nx)
        bar.update(n)
    bar.close()
    info = FieldInfo(field.info.label, field.info.name, field.info.symmetry,
                     {**field.info.provenance, "baked": {"cell": step, "nodes": [nx, ny, nz],
                                                         "band_cells": config.band_cells,
                                                         "coarse_stride": k}})
    out = BakedField(sdf, rgb, bounds, field.to_world.detach(), info)
    out.visibility = field.visibility
    return out
