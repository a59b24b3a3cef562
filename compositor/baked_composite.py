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

from regnf.neural_fields.baked_field import BakeConfig, bake, bake_cell, grid_nodes
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
    if isinstance(composite, CompositeField):
        masked = CompositeField(composite.scene, [], list(composite.removals), composite.config,
                                info=composite.scene.info)
        # One grid per library object, shared by its instances.
        fields = [masked, *{id(p.field): p.field for p in composite.placements}.values()]
    else:
        fields = [composite]
    cells = [bake_cell(f, cameras, config) for f in fields]
    total = sum(math.prod(grid_nodes(f.bounds, c, config.coarse_stride)) for f, c in zip(fields, cells))
    if total > config.max_total_nodes:  # before any baking
        raise ValueError(f"baking these {len(fields)} fields for these views needs {total:,} grid nodes "
                         f"({16 * total / 2**30:.1f} GB), more than max_total_nodes={config.max_total_nodes:,}: "
                         "render with the sphere tracer, or take coarser cells (cell_pixels)")
    baked = [bake(f, c, config, progress=progress) for f, c in zip(fields, cells)]
    if not isinstance(composite, CompositeField):
        return BakedComposite(baked[0], time.perf_counter() - t0, total)
    grid_of = {id(f): b for f, b in zip(fields[1:], baked[1:])}
    objects = [PlacedObject(grid_of[id(p.field)], p.mapped.matrix.cpu().numpy(), iid, tint)
               for p, iid, tint in zip(composite.placements, composite.instance_ids, composite.tints, strict=True)]
    field = CompositeField(baked[0], objects, [], composite.config, info=composite.info)
    return BakedComposite(field, time.perf_counter() - t0, total)
