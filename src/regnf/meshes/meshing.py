"""Marching-cubes meshes of fields, with outward faces and per-vertex colours.

The SDF is sampled on a regular grid over the bounds (chunked, no grad), the level set is
extracted by ``skimage.measure.marching_cubes`` with the grid spacing so that vertices land
in the field frame, faces are turned to face positive SDF, and each vertex is coloured as
seen from outside along its normal.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage.measure import marching_cubes

from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError
from regnf.core.threads import map_one_thread_each, usable_cores
from regnf.fields.field import DEFAULT_CHUNK, Field

from .mesh_writing import write_glb, write_ply

MESH_FORMATS = {".ply": "ply", ".glb": "glb"}
"""File suffix -> trimesh export type understood by :func:`save_mesh`."""


def grid_shape(bounds: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells per axis and grid spacing for ``resolution`` cells along the longest axis.

    Parameters
    ----------
    bounds : (2, 3) float
    resolution : int

    Returns
    -------
    cells : (3,) int
        At least 1 per axis, proportional to the extents.
    spacing : (3,) float
        ``extent / cells``; equal on all axes up to rounding of the cell counts.
    """
    ext = bounds[1] - bounds[0]
    cells = np.maximum(1, np.ceil(ext / ext.max() * resolution - 1e-9)).astype(np.int64)
    return cells, ext / cells


@torch.no_grad()
def sample_grid(
    field: Field,
    bounds: np.ndarray,
    cells: np.ndarray,
    chunk: int = DEFAULT_CHUNK,
    device: torch.device | str | None = None,
) -> np.ndarray:
    """SDF on the ``(cells + 1)`` grid nodes spanning ``bounds``.

    Parameters
    ----------
    field : Field
    bounds : (2, 3) float
    cells : (3,) int
    chunk : int
        Points per field evaluation; grid points are generated chunk by chunk so that
        memory stays bounded at high resolution.
    device : torch.device or str, optional
        Where to evaluate; the field's device by default.

    Returns
    -------
    (nx + 1, ny + 1, nz + 1) float32
    """
    dev = torch.device(device) if device is not None else field.device
    dims = torch.as_tensor(cells + 1, dtype=torch.long, device=dev)
    lo = torch.as_tensor(bounds[0], dtype=torch.float64, device=dev)
    step = torch.as_tensor((bounds[1] - bounds[0]) / cells, dtype=torch.float64, device=dev)
    total = int(dims.prod())
    out = np.empty(total, dtype=np.float32)

    # Chunks of flat node indices (x outer, z inner: C order of the volume), each written
    # into its own slice of ``out``.
    @torch.no_grad()
    def fill(start: int) -> None:
        flat = torch.arange(start, min(start + chunk, total), device=dev)
        ijk = torch.stack(
            [flat // (dims[1] * dims[2]), (flat // dims[2]) % dims[1], flat % dims[2]], dim=-1
        )
        pts = (lo + ijk.double() * step).float()
        out[start : start + flat.numel()] = field.sdf_chunked(pts, chunk, dev).cpu().numpy()

    # On the CPU, chunks side by side, one thread each: the bits of one after another on one
    # thread, on any machine, and faster (docs/decisions/implementation-speed.md).
    map_one_thread_each(fill, range(0, total, chunk), usable_cores() if dev.type == "cpu" else 1)
    return out.reshape(tuple(int(c) for c in cells + 1))


@torch.no_grad()
def extract_mesh(
    field: Field,
    resolution: int = 256,
    bounds: torch.Tensor | np.ndarray | None = None,
    level: float = 0.0,
    with_color: bool = True,
    chunk: int = DEFAULT_CHUNK,
    device: torch.device | str | None = None,
    in_world: bool = False,
) -> trimesh.Trimesh:
    """Mesh the ``level`` set of ``field`` by marching cubes.

    Parameters
    ----------
    field : Field
    resolution : int
        Cells along the LONGEST axis of ``bounds``; the others get proportionally many.
    bounds : (2, 3) float, optional
        Region to mesh in the field frame; the field's bounds by default.
    level : float
        Iso-value of the SDF.
    with_color : bool
        Colour vertices with ``field.color(v, -normal)`` (uint8 RGBA, alpha 255).
    chunk : int
        Points per field evaluation.
    device : torch.device or str, optional
        Where to evaluate; the field's device by default.
    in_world : bool
        Return the mesh in world units (apply ``field.to_world``) instead of the field frame.

    Returns
    -------
    trimesh.Trimesh
        Faces wound so that their normals point towards positive SDF (outward).

    Raises
    ------
    ValueError
        Bad arguments, a non-finite SDF on the grid, or no ``level`` crossing in the grid.
    """
    if int(resolution) != resolution or resolution < 2:
        raise RegnfError(f"resolution must be an integer >= 2, got {resolution}")
    b = field.bounds if bounds is None else bounds
    b = np.asarray(b.detach().cpu().numpy() if isinstance(b, torch.Tensor) else b, dtype=np.float64)
    if b.shape != (2, 3) or not np.all(np.isfinite(b)) or not np.all(b[1] > b[0]):
        raise RegnfError(f"bounds must be a finite (2, 3) box with max > min, got {b.tolist()}")
    dev = torch.device(device) if device is not None else field.device

    cells, spacing = grid_shape(b, int(resolution))
    vol = sample_grid(field, b, cells, chunk, dev)
    if not np.all(np.isfinite(vol)):
        raise RegnfError("the field returned non-finite SDF values on the meshing grid")
    if not (vol.min() < level < vol.max()):
        raise RegnfError(
            f"no surface at level {level} in the grid: SDF ranges over [{vol.min():.4g}, "
            f"{vol.max():.4g}] inside bounds {b.tolist()}"
        )
    verts, faces, _, _ = marching_cubes(vol, level=level, spacing=tuple(spacing))
    verts = verts.astype(np.float64) + b[0]
    faces = faces.astype(np.int64)

    # Outward normals from the field itself, then wind faces to agree with them. skimage's
    # winding is consistent over the mesh, so one global vote decides whether to flip.
    vt = torch.as_tensor(verts, dtype=torch.float32, device=dev)
    grads = torch.cat([field.gradient(vt[i : i + chunk]) for i in range(0, vt.shape[0], chunk)])
    normals = torch.nn.functional.normalize(grads.double(), dim=-1).cpu().numpy()
    tri = verts[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if np.sum(np.einsum("ij,ij->i", face_n, normals[faces].sum(axis=1))) < 0:
        faces = faces[:, ::-1].copy()

    colors = vertex_colors(field, verts, normals, chunk, dev) if with_color else None

    mesh = trimesh.Trimesh(
        vertices=verts, faces=faces, vertex_normals=normals, vertex_colors=colors, process=False
    )
    if in_world:
        mesh.apply_transform(field.to_world.detach().cpu().numpy())
    return mesh


@torch.no_grad()
def vertex_colors(field: Field, vertices: np.ndarray, normals: np.ndarray, chunk: int = DEFAULT_CHUNK,
                  device: torch.device | str | None = None) -> np.ndarray:
    """(n, 4) uint8 RGBA (alpha 255): the field's colour at ``vertices`` (n, 3), seen from
    outside along the unit ``normals`` (n, 3), both in the field frame."""
    dev = torch.device(device) if device is not None else field.device
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float32, device=dev)
    n = torch.as_tensor(np.array(normals), dtype=torch.float32, device=dev)
    rgb = field.color_chunked(v, -n, chunk=chunk, device=dev).cpu().numpy()
    rgb8 = np.clip(np.round(np.clip(rgb, 0.0, 1.0) * 255.0), 0, 255).astype(np.uint8)
    return np.concatenate([rgb8, np.full((rgb8.shape[0], 1), 255, np.uint8)], axis=1)


def save_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` atomically as .ply or .glb (chosen by the suffix), its vertices where they are.

    A PLY stores float64 vertices; a .glb (float32 by the format) stores them relative to an
    origin when they lie far from zero (:mod:`regnf.meshes.mesh_writing`).

    Returns
    -------
    Path
        The written path.

    Raises
    ------
    ValueError
        For any other suffix.
    """
    dest = Path(path)
    kind = MESH_FORMATS.get(dest.suffix.lower())
    if kind is None:
        raise RegnfError(f"mesh path must end in .ply or .glb, got {dest.name!r}")
    with atomic_path(dest) as tmp:
        (write_ply if kind == "ply" else write_glb)(mesh, tmp)
    return dest
