"""Baked fields on disk: a ``.safetensors`` file of the two grids and a JSON header. Never pickle.

A data set rendered with baked grids (``regnf generate --render.renderer baked``) bakes each
field once and every worker reads the same grids from these files. The header (safetensors
metadata under :data:`HEADER_KEY`) records the grid's bounds, its ``to_world`` and the field's
description; :func:`load_baked` checks every one of them and the tensors' shapes before the
field is built, and names the file in the one-line error of anything it refuses.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as save_to_bytes

from regnf.core.atomic_io import write_bytes
from regnf.core.errors import RegnfError
from regnf.core.fresh_memory import in_fresh_memory
from regnf.fields.field import FieldInfo, Symmetry
from regnf.render.baked_field import RGB_STORAGE, BakedField

HEADER_KEY = "regnf-baked"
"""Key of the JSON header in the safetensors metadata."""
FORMAT_VERSION = 1
"""Written by :func:`save_baked`."""
BYTES_PER_NODE = 4 + 3 * torch.finfo(RGB_STORAGE).bits // 8
"""Bytes a grid node takes in a baked-grid file: its float32 distance and its three stored colour channels."""
MAX_NODES = 2**30
"""Most grid nodes a file may declare (16 GB of float32 distance and colour); far above what
:class:`~regnf.render.baked_field.BakeConfig` makes (at most 2^25 a field by default)."""


class BakedFileError(RegnfError):
    """A baked-grid file that cannot be used; the one-line message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: {' '.join(problem.split())}")


def save_baked(field: BakedField, path: str | os.PathLike) -> Path:
    """Write ``field``'s grids and header to ``path`` (``.safetensors``) atomically; returns the path."""
    path = Path(path)
    if path.suffix != ".safetensors":
        raise BakedFileError(path, "baked grids are .safetensors files")
    header = {
        "version": FORMAT_VERSION,
        "bounds": field.bounds.detach().cpu().double().tolist(),
        "to_world": field.to_world.detach().cpu().double().tolist(),
        "label": field.info.label,
        "name": field.info.name,
        "symmetry": field.info.symmetry.to_json(),
        "provenance": field.info.provenance,
    }
    tensors = {"sdf": field.sdf_grid[0, 0].detach().cpu().contiguous(),
               "rgb": field.rgb_grid[0].detach().cpu().to(RGB_STORAGE).contiguous()}  # exact: kept so
    # Serialised in memory and written by atomic_io (a kill leaves no half file under the name).
    write_bytes(path, save_to_bytes(tensors, metadata={HEADER_KEY: json.dumps(header)}))
    return path


def _matrix(path: Path, header: dict, key: str, shape: tuple[int, int]) -> torch.Tensor:
    try:
        m = np.asarray(header[key], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise BakedFileError(path, f"header {key!r} is missing or not numeric ({exc})") from None
    if m.shape != shape or not np.isfinite(m).all():
        raise BakedFileError(path, f"header {key!r} must be a finite {shape} array, got shape {m.shape}")
    return torch.as_tensor(m, dtype=torch.float64)


def load_baked(path: str | os.PathLike, device: torch.device | str = "cpu") -> BakedField:
    """The :class:`BakedField` stored at ``path`` by :func:`save_baked`, on ``device``.

    Raises
    ------
    BakedFileError
        (a ``ValueError``) The file is missing, not a safetensors file, of another version, or
        its header or grids are malformed (shapes, sizes, non-finite bounds or distances).
    """
    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            if HEADER_KEY not in meta:
                raise BakedFileError(path, f"no {HEADER_KEY!r} header: not a regnf baked-grid file")
            header = json.loads(meta[HEADER_KEY])
            if not isinstance(header, dict) or header.get("version") != FORMAT_VERSION:
                raise BakedFileError(path, f"baked-grid format version {header.get('version') if isinstance(header, dict) else None!r}, "
                                     f"this regnf reads {FORMAT_VERSION}; bake again")
            if set(f.keys()) != {"sdf", "rgb"}:
                raise BakedFileError(path, f"expected the tensors 'sdf' and 'rgb', found {sorted(f.keys())}")
            shape = tuple(f.get_slice("sdf").get_shape())
            if len(shape) != 3 or min(shape) < 2 or math.prod(shape) > MAX_NODES:
                raise BakedFileError(path, f"'sdf' must be (nz, ny, nx) with 2 to {MAX_NODES:,} nodes, got {shape}")
            if tuple(f.get_slice("rgb").get_shape()) != (3, *shape):
                raise BakedFileError(path, f"'rgb' must be (3, *{shape}), got {tuple(f.get_slice('rgb').get_shape())}")
            bounds = _matrix(path, header, "bounds", (2, 3))
            to_world = _matrix(path, header, "to_world", (4, 4))
            if not bool((bounds[1].float() > bounds[0].float()).all()):
                raise BakedFileError(path, f"header 'bounds' must have lo < hi on every axis, got {bounds.tolist()}")
            # The colour as stored (half precision): BakedField converts it once.
            sdf, rgb = in_fresh_memory(f.get_tensor("sdf"), torch.float32), f.get_tensor("rgb")
    except (OSError, SafetensorError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BakedFileError(path, f"cannot read baked grids ({type(exc).__name__}: {exc})") from None
    if not bool(torch.isfinite(sdf).all()):
        raise BakedFileError(path, "the distance grid holds non-finite values")
    try:
        info = FieldInfo(str(header.get("label", "object")), str(header.get("name", "")),
                         Symmetry.from_json(header.get("symmetry")), dict(header.get("provenance") or {}))
        return BakedField(sdf, rgb, bounds, to_world, info).to(device)
    except (TypeError, ValueError) as exc:
        raise BakedFileError(path, f"malformed header ({exc})") from None
