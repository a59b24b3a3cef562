"""A composite with its fields baked: every sphere-tracing step reads grids, not networks.

The scene less its removal regions is baked once as one field (the regions' cuts are then grid
values too), and each placed library field once in its own frame, shared by every instance
that shows it; the placements keep their similarities and tints. See
:mod:`regnf.neural_fields.baked_field` for the grids and how their cell is chosen.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import NamedTuple

from regnf.neural_fields.baked_field import BakeConfig, BakedField, bake, bake_cell, grid_nodes
from regnf.neural_fields.camera import Camera
from regnf.neural_fields.field import Field

from .composite_field import CompositeField
from .placement import PlacedObject


class BakedComposite(NamedTuple):
    """A baked composite and what baking it cost."""

    field: Field
    """The composite of the baked fields (no removal regions: they are in the scene's grid), or
    the baked field of a field that is not a composite."""
    seconds: float
    """Wall time of the baking."""
    nodes: int
    """Grid nodes over every baked field."""


def bake_for_views(composite: Field, cameras: Sequence[Camera], config: BakeConfig | None = None,
                   progress: bool = False) -> BakedComposite:
    """``composite`` with its masked scene and its library fields baked for ``cameras``.

    Parameters
    ----------
    composite : Field
        A :class:`CompositeField`; any other field is baked whole.
    cameras : sequence of Camera
        The views to be rendered (metres): each field's cell follows their pixel footprint
        (:func:`~regnf.neural_fields.baked_field.bake_cell`).
    config : BakeConfig, optional
        Defaults to ``BakeConfig()``.
    progress : bool
        Show a progress bar per baked field.
    """
    config = config or BakeConfig()
    t0 = time.perf_counter()
    if not isinstance(composite, CompositeField):
        _check_total([composite], cameras, config)
        whole = bake(composite, bake_cell(composite, cameras, config), config, progress=progress)
        return BakedComposite(whole, time.perf_counter() - t0, whole.sdf_grid.numel())
    masked = CompositeField(composite.scene, [], list(composite.removals), composite.config,
                            info=composite.scene.info)
    library = list({id(p.field): p.field for p in composite.placements}.values())
    _check_total([masked, *library], cameras, config)  # before any baking
    scene = bake(masked, bake_cell(masked, cameras, config), config, progress=progress)
    baked: dict[int, BakedField] = {}  # by the library field's identity: one grid per object

    def baked_library(f: Field) -> BakedField:
        if id(f) not in baked:
            baked[id(f)] = bake(f, bake_cell(f, cameras, config), config, progress=progress)
        return baked[id(f)]

    objects = [PlacedObject(baked_library(p.field), p.mapped.matrix.cpu().numpy(), iid, tint)
               for p, iid, tint in zip(composite.placements, composite.instance_ids, composite.tints, strict=True)]
    field = CompositeField(scene, objects, [], composite.config, info=composite.info)
    nodes = sum(b.sdf_grid.numel() for b in (scene, *baked.values()))
    return BakedComposite(field, time.perf_counter() - t0, nodes)


def _check_total(fields: Sequence[Field], cameras: Sequence[Camera], config: BakeConfig) -> None:
    """Raise ``ValueError`` if baking ``fields`` for ``cameras`` needs more than
    ``config.max_total_nodes`` grid nodes."""
    total = sum(math.prod(grid_nodes(f.bounds, bake_cell(f, cameras, config), config.coarse_stride)) for f in fields)
    if total > config.max_total_nodes:
        raise ValueError(f"baking these {len(fields)} fields for these views needs {total:,} grid nodes "
                         f"({16 * total / 2**30:.1f} GB), more than max_total_nodes={config.max_total_nodes:,}: "
                         "render with the sphere tracer, or take coarser cells (cell_pixels)")
