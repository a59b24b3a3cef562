"""Checkpoints: safetensors weights plus a JSON header, validated on load. Never pickle.

The JSON header lives in the safetensors metadata under the key ``regnf`` and records the
architecture, bounds, ``to_world``, class, symmetry and provenance, so one file is the
whole field and a reader can check every tensor before building anything.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from neural_fields.field import FieldInfo, Symmetry
from neural_fields.neural_sdf import ARCHITECTURE, NeuralSDF, NeuralSDFConfig
from synthetic.atomic_io import atomic_path

HEADER_KEY = "regnf"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def field_header(field: NeuralSDF) -> dict:
    """The JSON header describing ``field`` (everything but the weights)."""
    return {
        "format_version": FORMAT_VERSION,
        "architecture": ARCHITECTURE,
        "config": field.config.to_json(),
        "bounds": field.bounds.tolist(),
        "to_world": field.to_world.tolist(),
        "label": field.info.label,
        "name": field.info.name,
        "symmetry": field.info.symmetry.to_json(),
        "provenance": field.info.provenance,
    }


def save_field(field: NeuralSDF, path: str | os.PathLike) -> Path:
    """Write ``field`` to ``path`` (``.safetensors``) atomically; returns the path."""
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(path, "checkpoints are .safetensors files")
    header = json.dumps(field_header(field))
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in field.state_dict().items()}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={HEADER_KEY: header})
    return path


def read_header(path: str | os.PathLike) -> dict:
    """Read and validate the JSON header of a checkpoint without loading weights."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(path, "file does not exist")
    if not path.is_file():
        raise CheckpointError(path, "is not a file")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(path, f"not a readable safetensors file ({exc})") from exc
    if HEADER_KEY not in meta:
        raise CheckpointError(path, f"no '{HEADER_KEY}' JSON header (not a regnf checkpoint)")
    try:
        header = json.loads(meta[HEADER_KEY])
    except json.JSONDecodeError as exc:
        raise CheckpointError(path, f"the JSON header is corrupted ({exc})") from exc
    if not isinstance(header, dict):
        raise CheckpointError(path, "the JSON header is not an object")
    arch = header.get("architecture")
    if arch != ARCHITECTURE:
        raise CheckpointError(path, f"unknown architecture {arch!r} (expected {ARCHITECTURE!r})")
    for key in ("config", "bounds", "to_world"):
        if key not in header:
            raise CheckpointError(path, f"the header lacks '{key}'")
    _check_matrix(path, "bounds", header["bounds"], (2, 3))
    _check_matrix(path, "to_world", header["to_world"], (4, 4))
    return header


def load_field(path: str | os.PathLike, device: torch.device | str = "cpu") -> NeuralSDF:
    """Load a checkpoint written by :func:`save_field`, validating every tensor.

    Raises
    ------
    CheckpointError
        Missing or truncated file, bad header, unknown architecture, missing / unexpected
        tensors, wrong shapes or dtypes, non-finite weights.
    """
    path = Path(path)
    header = read_header(path)
    try:
        config = NeuralSDFConfig.from_json(header["config"])
    except (TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(path, f"bad architecture config: {exc}") from exc
    try:
        info = FieldInfo(
            label=str(header.get("label", "object")),
            name=str(header.get("name", "")),
            symmetry=Symmetry.from_json(header.get("symmetry")),
            provenance=dict(header.get("provenance", {})),
        )
        bounds = torch.tensor(header["bounds"], dtype=torch.float32)
        to_world = torch.tensor(header["to_world"], dtype=torch.float64)
    except (TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(path, f"bad header: {exc}") from exc
    try:
        # Build a weightless skeleton first (meta device: nothing is allocated), so that a
        # forged header asking for a huge grid is caught by the shape check below instead
        # of exhausting memory.
        with torch.device("meta"):
            skeleton = NeuralSDF(config, bounds=bounds, to_world=to_world, info=info)
    except (TypeError, ValueError, AttributeError, RuntimeError) as exc:
        raise CheckpointError(path, f"cannot build the field from the header: {exc}") from exc
    expected = {k: (tuple(v.shape), v.dtype) for k, v in skeleton.state_dict().items()}
    try:
        with safe_open(str(path), framework="pt") as f:
            names = set(f.keys())
            missing = sorted(set(expected) - names)
            extra = sorted(names - set(expected))
            if missing:
                raise CheckpointError(path, f"missing tensors {missing[:5]}")
            if extra:
                raise CheckpointError(path, f"unexpected tensors {extra[:5]}")
            for name, (shape, _) in expected.items():
                stored = tuple(f.get_slice(name).get_shape())
                if stored != shape:
                    raise CheckpointError(path, f"tensor '{name}' has shape {stored}, expected {shape}")
            state = {}
            for name, (_, dtype) in expected.items():
                t = f.get_tensor(name)
                if t.dtype != dtype:
                    raise CheckpointError(path, f"tensor '{name}' has dtype {t.dtype}, expected {dtype}")
                if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                    raise CheckpointError(path, f"tensor '{name}' has non-finite values")
                state[name] = t
    except CheckpointError:
        raise
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(path, f"truncated or corrupted tensor data ({exc})") from exc
    field = NeuralSDF(config, bounds=bounds, to_world=to_world, info=info)
    field.load_state_dict(state)
    return field.to(device)


def _check_matrix(path: Path, key: str, value: object, shape: tuple[int, int]) -> None:
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(path, f"'{key}' is not a numeric matrix") from exc
    if tuple(t.shape) != shape:
        raise CheckpointError(path, f"'{key}' has shape {tuple(t.shape)}, expected {shape}")
    if not all(math.isfinite(v) for v in t.flatten().tolist()):
        raise CheckpointError(path, f"'{key}' has non-finite values")
