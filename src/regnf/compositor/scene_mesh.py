"""The scene as an edit shows it, as a mesh: the scene field less every instance's removal region.

Other tools (Blender, Isaac Sim, usdview) cannot evaluate fields; a stage hands them meshes. The
scene's own proxy still holds every object the capture saw, so each substituted library object
would stand inside the blob of the one it replaces. :func:`edited_scene_mesh` meshes the
scene field with the compositor's own masking (:func:`regnf.compositor.baked_composite.masked_scene`,
the same removal regions the renders cut out): marching cubes on a grid of
``SceneMeshConfig.cell`` metres, then every vertex moved onto the zero set along the gradient
(Newton steps), so the vertices lie on the surface the renders show. Faces stay chords: across
the crease where a removal region cuts the surface, a face cuts the corner by a fraction of a
cell. The distance of the finished mesh to the field's zero set is measured on points spread
over its faces and reported with it.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
import trimesh

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.meshes.meshing import extract_mesh, vertex_colors

from .baked_composite import masked_scene
from .from_stage import composite_from_stage
from .stage_config import StageCompositeConfig


@dataclass(frozen=True)
class SceneMeshConfig:
    """How the edited scene is meshed."""

    cell: float = 0.02
    """Marching-cubes cell, metres."""
    snap_steps: int = 3
    """Newton steps that move each vertex onto the zero set."""
    check_points: int = 200_000
    """Points spread over the faces on which the distance to the zero set is measured."""
    max_cells: int = 80_000_000
    """Most grid nodes the meshing may evaluate (a smaller ``cell`` over a large room is refused)."""
    composite: StageCompositeConfig = field(default_factory=StageCompositeConfig)
    """Removal settings (the mode is always substitute)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cell) and self.cell > 0):
            raise RegnfError(f"the scene mesh cell must be > 0 metres, got {self.cell}")
        if self.snap_steps < 0 or self.check_points < 1 or self.max_cells < 8:
            raise RegnfError("snap_steps must be >= 0, check_points >= 1 and max_cells >= 8")


class SceneMesh(NamedTuple):
    """An edited scene's mesh and how close it lies to the field's zero set."""

    mesh: trimesh.Trimesh
    """Room metres, faces outward, vertex colours (RGBA uint8) and normals."""
    distance_p99: float
    """99th percentile of |SDF| over points spread on the faces, metres."""
    distance_max: float
    """Largest |SDF| over those points, metres."""
    removals: int
    """Removal regions cut out of the scene."""


def snap_to_zero_set(field: Field, points: np.ndarray, steps: int) -> np.ndarray:
    """Move ``points`` (n, 3) float, field frame, onto the zero set by Newton steps ``x - f grad f / |grad f|^2``."""
    x = torch.as_tensor(points, dtype=torch.float32, device=field.device)
    for _ in range(steps):
        moved = []
        for i in range(0, x.shape[0], 65536):  # chunks of points bound the autograd graph
            xi = x[i:i + 65536]
            f, g = field.sdf_and_gradient(xi)
            f, g = f.detach().reshape(-1, 1), g.detach()
            step = f * g / g.square().sum(dim=-1, keepdim=True).clamp_min(1e-12)
            # A step is at most the SDF itself in length (where the gradient is weak, it would jump).
            limit = f.abs() / step.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            moved.append(xi - step * limit.clamp(max=1.0))
        x = torch.cat(moved)
    return x.detach().cpu().double().numpy()


def surface_distance(field: Field, mesh: trimesh.Trimesh, points: int, seed: int = 0) -> np.ndarray:
    """|SDF| (field units) at ``points`` spread uniformly (by area) over the faces of ``mesh`` (field frame)."""
    pts, _ = trimesh.sample.sample_surface(mesh, int(points), seed=seed)
    sdf = field.sdf_chunked(torch.as_tensor(pts, dtype=torch.float32, device=field.device))
    return sdf.abs().double().cpu().numpy()


def edited_scene_mesh(stage: str | os.PathLike, config: SceneMeshConfig = SceneMeshConfig(),
                      device: torch.device | str = "cpu") -> SceneMesh:
    """Mesh the scene of ``stage`` less the removal regions of all its instances (see the module).

    Parameters
    ----------
    stage : str or PathLike
        A regnf stage, replacement layer or package.
    config : SceneMeshConfig
    device : torch.device or str

    Returns
    -------
    SceneMesh

    Raises
    ------
    ValueError
        The grid at ``config.cell`` over the scene would have more than ``config.max_cells``
        nodes (before any evaluation).
    """
    comp = composite_from_stage(stage, StageCompositeConfig(**{**config.composite.__dict__, "mode": "substitute"}),
                                device)
    masked = masked_scene(comp.field) if comp.field.removals else comp.field.scene
    scale = masked.world_scale
    bounds = masked.bounds.detach().cpu().double().numpy()
    extent = (bounds[1] - bounds[0]) * scale
    resolution = max(2, math.ceil(float(extent.max()) / config.cell))
    nodes = float(np.prod(np.ceil(extent / extent.max() * resolution) + 1))
    if nodes > config.max_cells:
        raise RegnfError(f"meshing the scene ({extent.round(2).tolist()} m) at {config.cell * 100:g} cm cells "
                         f"needs {nodes:,.0f} grid nodes, more than {config.max_cells:,}; use a larger cell")
    mesh = extract_mesh(masked, resolution=resolution, with_color=False)
    mesh.vertices = snap_to_zero_set(masked, np.asarray(mesh.vertices), config.snap_steps)
    distance = surface_distance(masked, mesh, config.check_points) * scale
    mesh = extract_colors(masked, mesh)
    mesh.apply_transform(masked.to_world.detach().cpu().double().numpy())
    return SceneMesh(mesh, float(np.quantile(distance, 0.99)), float(distance.max()), len(comp.field.removals))


def extract_colors(field: Field, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` (field frame) with vertex normals from its faces and colours seen from outside along them."""
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    colors = vertex_colors(field, np.asarray(mesh.vertices), normals)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_normals=normals, vertex_colors=colors, process=False)
