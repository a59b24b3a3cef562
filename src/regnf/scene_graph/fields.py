"""Field records from checkpoints: validate the checkpoint, mesh a proxy by marching cubes."""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from regnf.fields.field import Field, Symmetry
from regnf.io.checkpoint import CheckpointError, load_field, read_header
from regnf.meshes.meshing import extract_mesh
from regnf.meshes.source_mesh import SourceMeshError, read_source_mesh, source_mesh_file

from .embedded_checkpoint import checkpoint_file
from .errors import StageError
from .model import FieldRecord, ProxyMesh


@dataclass(frozen=True)
class ProxyConfig:
    """How proxy meshes are made."""

    resolution: int = 48
    """Marching-cubes cells along the longest axis of the field's bounds (a preview, not a scan)."""
    with_color: bool = True
    """Colour the proxy's vertices from the field."""
    device: str = "cpu"
    """Torch device on which the field is evaluated."""


def proxy_from_trimesh(mesh: trimesh.Trimesh) -> ProxyMesh:
    """A :class:`ProxyMesh` from a triangle mesh in metres (vertex colours kept if any)."""
    colors = None
    vc = getattr(mesh.visual, "vertex_colors", None)
    if mesh.visual.kind == "vertex" and vc is not None and len(vc) == len(mesh.vertices):
        colors = (np.asarray(vc)[:, :3] / 255.0).astype(np.float32)
    return ProxyMesh(
        np.asarray(mesh.vertices, dtype=np.float32),
        np.asarray(mesh.faces, dtype=np.int32),
        colors,
    )


def checkpoint_name(checkpoint: str | os.PathLike, prim: str) -> str:
    """The field name in a checkpoint's header (its file stem if it has none)."""
    try:
        header = read_header(checkpoint)
    except CheckpointError as exc:
        raise StageError(exc.path, prim, exc.problem) from exc
    return str(header.get("name") or Path(checkpoint).stem)


def field_record(
    checkpoint: str | os.PathLike,
    prim: str,
    config: ProxyConfig | None = None,
    proxy: trimesh.Trimesh | None = None,
) -> FieldRecord:
    """Read and validate a checkpoint and make its :class:`FieldRecord`.

    Parameters
    ----------
    checkpoint : str or PathLike
        A regnf checkpoint (.safetensors).
    prim : str
        The prim the field will become (named in errors).
    config : ProxyConfig, optional
    proxy : trimesh.Trimesh, optional
        A proxy mesh in metres to use instead of marching cubes of the field.

    The source mesh kept beside a distilled checkpoint
    (:func:`regnf.meshes.source_mesh.source_mesh_file`) comes with the record.

    Raises
    ------
    StageError
        A missing or corrupted checkpoint or source mesh, or a field with no surface to mesh.
    """
    cfg = config or ProxyConfig()
    path = Path(checkpoint).absolute()
    try:
        header = read_header(path)
        field = load_field(path, device=cfg.device)
    except CheckpointError as exc:
        raise StageError(exc.path, prim, exc.problem) from exc
    try:
        source = read_source_mesh(path)
    except SourceMeshError as exc:
        raise StageError(source_mesh_file(path), prim, str(exc).removeprefix(f"{source_mesh_file(path)}: ")) from exc
    if proxy is None:
        try:
            mesh = extract_mesh(field, cfg.resolution, with_color=cfg.with_color, in_world=True)
        except ValueError as exc:
            raise StageError(path, prim, f"cannot mesh a proxy: {exc}") from exc
        proxy_mesh = proxy_from_trimesh(mesh)
    else:
        proxy_mesh = proxy_from_trimesh(proxy)
    return FieldRecord(
        name=str(header.get("name") or path.stem),
        label=str(header.get("label") or "object"),
        checkpoint=path,
        to_world=np.asarray(header["to_world"], dtype=np.float64),
        bounds=np.asarray(header["bounds"], dtype=np.float64),
        symmetry_order=Symmetry.from_json(header.get("symmetry")).order,
        provenance=dict(header.get("provenance") or {}),
        proxy=proxy_mesh,
        source_mesh=source,
    )


TO_WORLD_ATOL = 1e-9
"""A stage's recorded to_world must match its checkpoint's to this (absolute, per entry)."""


def load_record_field(stage: Path, prim: str, rec: FieldRecord, device: torch.device | str,
                      loaded: MutableMapping[str, Field] | None = None) -> Field:
    """Load ``rec``'s checkpoint (from inside a package too) and check its ``to_world``.

    Parameters
    ----------
    stage : Path
        The stage ``rec`` was read from (named in errors).
    prim : str
        Where in the stage the record is (named in errors).
    rec : FieldRecord
    device : torch.device or str
    loaded : mutable mapping, optional
        Fields already loaded, by checkpoint and device: each checkpoint is loaded once.

    Raises
    ------
    StageError
        The checkpoint cannot be loaded, or its ``to_world`` differs from the stage's record by
        more than :data:`TO_WORLD_ATOL`.
    """
    key = f"{rec.checkpoint}@{device}"
    if loaded is not None and key in loaded:
        return loaded[key]
    try:
        with checkpoint_file(rec.checkpoint) as ckpt:
            field = load_field(ckpt, device)
    except CheckpointError as exc:
        raise StageError(rec.checkpoint, prim, f"checkpoint of {rec.name!r} in {stage}: {exc.problem}") from exc
    got = field.to_world.detach().cpu().double().numpy()
    err = float(np.abs(got - rec.to_world).max())
    if err > TO_WORLD_ATOL:
        raise StageError(stage, prim, f"the stage records a to_world for {rec.name!r} that differs from "
                         f"its checkpoint's {rec.checkpoint} by {err:.3g}")
    if loaded is not None:
        loaded[key] = field
    return field
