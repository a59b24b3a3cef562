"""What a checkpoint's header may ask for, checked before anything is built or allocated, and the
error every problem with a checkpoint raises (:mod:`regnf.io.checkpoint`)."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch

from regnf.core.errors import RegnfError
from regnf.fields.neural_sdf import NeuralSDFConfig, parameter_count

# A header is checked against these before any model (not even a weightless meta-device
# skeleton, which builds one module per level and per layer) is constructed: a forged
# ``levels = 10**8`` otherwise loops for minutes, and a forged size allocates gigabytes.
# Each is far above anything regnf trains; pass ``ArchitectureLimits(...)`` to go beyond.

MAX_LEVELS = 32
"""Grid levels (presets: 6-7; instant-NGP: 16). Levels are a geometric series from the base
to the finest resolution: beyond 32 they are a few percent apart and only cost memory."""

MAX_HIDDEN_LAYERS = 64
"""Hidden layers of the SDF MLP (presets: 2). One module each."""

MAX_WIDTH = 4096
"""``hidden_dim``, ``geo_feature_dim`` and ``color_hidden_dim`` (presets: 64, 15, 64)."""

MAX_FEATURES_PER_LEVEL = 64
"""Feature channels per grid level (presets: 4; instant-NGP: 2)."""

MAX_RESOLUTION = 2**16
"""``base_resolution`` and ``finest_resolution``, cells along the longest axis (presets: up
to 256). Also keeps the hash encoding's integer corner products far from int64 overflow."""

MAX_HASH_TABLE_SIZE_LOG2 = 26
"""Hash encoding: at most 2**26 rows per level (instant-NGP: 2**19 to 2**24)."""

MAX_PARAMETERS = 2**28
"""Trainable values in all (268 M, 1 GiB of float32; presets: 4 M for an object, about 30 M
for a room). Bounds what building the field allocates, whatever the other values combine to."""

MAX_VISIBILITY_RESOLUTION = 1024
"""Voxels along any axis of a visibility grid (training's default: 128 on the longest)."""

MAX_VISIBILITY_VOXELS = 2**26
"""Voxels of a visibility grid in all (67 M: 64 MiB of uint8 counts and the 256 MiB float32
lookup volume built on load; training's default: at most 2.1 M)."""


@dataclass(frozen=True)
class ArchitectureLimits:
    """The largest architecture a checkpoint header may ask for (defaults: the MAX_* constants)."""

    max_levels: int = MAX_LEVELS
    """See :data:`MAX_LEVELS`."""
    max_hidden_layers: int = MAX_HIDDEN_LAYERS
    """See :data:`MAX_HIDDEN_LAYERS`."""
    max_width: int = MAX_WIDTH
    """See :data:`MAX_WIDTH`."""
    max_features_per_level: int = MAX_FEATURES_PER_LEVEL
    """See :data:`MAX_FEATURES_PER_LEVEL`."""
    max_resolution: int = MAX_RESOLUTION
    """See :data:`MAX_RESOLUTION`."""
    max_hash_table_size_log2: int = MAX_HASH_TABLE_SIZE_LOG2
    """See :data:`MAX_HASH_TABLE_SIZE_LOG2`."""
    max_parameters: int = MAX_PARAMETERS
    """See :data:`MAX_PARAMETERS`."""
    max_visibility_resolution: int = MAX_VISIBILITY_RESOLUTION
    """See :data:`MAX_VISIBILITY_RESOLUTION`."""
    max_visibility_voxels: int = MAX_VISIBILITY_VOXELS
    """See :data:`MAX_VISIBILITY_VOXELS`."""


class CheckpointError(RegnfError):
    """A checkpoint that cannot be used; the one-line message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = Path(path)
        # One line, even when the problem quotes a library's multi-line message.
        self.problem = re.sub(r"\s*[\r\n]+\s*", " ", problem)
        super().__init__(f"{self.path}: {self.problem}")


def check_architecture(
    config: NeuralSDFConfig, extent: torch.Tensor, limits: ArchitectureLimits | None = None
) -> int:
    """Refuse an architecture beyond ``limits``, cheaply (nothing is built or allocated).

    Parameters
    ----------
    config : NeuralSDFConfig
        A parsed (type-checked) config.
    extent : (3,) float
        Size of the field's bounds box (its aspect ratio sets the dense grids' shapes).
    limits : ArchitectureLimits, optional
        Defaults to the module's MAX_* constants.

    Returns
    -------
    int
        The field's number of trainable values.

    Raises
    ------
    ValueError
        Naming the first value over its limit, or the parameter count.
    """
    lim = limits or ArchitectureLimits()
    bounded = [
        ("levels", config.levels, lim.max_levels, "max_levels"),
        ("hidden_layers", config.hidden_layers, lim.max_hidden_layers, "max_hidden_layers"),
        ("hidden_dim", config.hidden_dim, lim.max_width, "max_width"),
        ("geo_feature_dim", config.geo_feature_dim, lim.max_width, "max_width"),
        ("color_hidden_dim", config.color_hidden_dim, lim.max_width, "max_width"),
        ("features_per_level", config.features_per_level, lim.max_features_per_level,
         "max_features_per_level"),
        ("base_resolution", config.base_resolution, lim.max_resolution, "max_resolution"),
        ("finest_resolution", config.finest_resolution, lim.max_resolution, "max_resolution"),
        ("hash_table_size_log2", config.hash_table_size_log2, lim.max_hash_table_size_log2,
         "max_hash_table_size_log2"),
    ]
    for name, value, limit, knob in bounded:
        if value > limit:
            raise RegnfError(f"{name} = {value} exceeds the limit {limit} (ArchitectureLimits.{knob})")
    count = parameter_count(config, extent)  # one step per level: levels is bounded above
    if count > lim.max_parameters:
        raise RegnfError(
            f"{count} parameters exceed the limit {lim.max_parameters} (ArchitectureLimits.max_parameters)"
        )
    return count


def check_visibility(meta: Mapping, limits: ArchitectureLimits | None = None) -> int:
    """Refuse a visibility grid beyond ``limits``, from its parsed metadata (nothing allocated).

    Parameters
    ----------
    meta : Mapping
        :meth:`VisibilityGrid.parse_json` of the header's block.
    limits : ArchitectureLimits, optional
        Defaults to the module's MAX_* constants.

    Returns
    -------
    int
        The grid's number of voxels.

    Raises
    ------
    ValueError
        Naming the axis or the voxel count over its limit.
    """
    lim = limits or ArchitectureLimits()
    resolution = meta["resolution"]
    for axis, n in zip("xyz", resolution):
        if n > lim.max_visibility_resolution:
            raise RegnfError(
                f"{n} voxels along {axis} exceed the limit {lim.max_visibility_resolution} "
                "(ArchitectureLimits.max_visibility_resolution)"
            )
    voxels = math.prod(resolution)
    if voxels > lim.max_visibility_voxels:
        raise RegnfError(
            f"{voxels} voxels exceed the limit {lim.max_visibility_voxels} "
            "(ArchitectureLimits.max_visibility_voxels)"
        )
    return voxels
