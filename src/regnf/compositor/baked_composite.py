"""A composite with its fields baked: every sphere-tracing step reads grids, not networks.

The scene less its removal regions is baked once as one field (the regions' cuts are then grid
values too), and each placed library field once in its own frame, shared by every instance
that shows it; the placements keep their similarities and tints. A library field's cell
follows the pixel footprint where it stands in the scene (its placement), the finest over
the places it stands in. See :mod:`regnf.render.baked_field` for the grids.

Two entry points: :func:`bake_for_views` bakes a composite for the views about to be rendered
(``regnf render --render.renderer baked``); :func:`bake_grids` bakes a masked scene and a set of
library objects once, and :func:`with_grids` puts those grids in place of a composite's fields,
for the many composites of one stage that ``regnf generate`` renders.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from regnf.core.errors import RegnfError
from regnf.core.threads import map_one_thread_each
from regnf.fields.field import Field
from regnf.render.baked_field import BakeConfig, BakedField, bake, bake_cell, grid_nodes
from regnf.render.camera import Camera
from regnf.render.sphere_tracer import SphereTracerConfig

from .composite_field import CompositeField


class BakedComposite(NamedTuple):
    """A baked composite and what baking it cost."""

    field: Field
    """The composite of the baked fields (no removal regions: they are in the scene's grid), or
    the baked field of a field that is not a composite."""
    seconds: float
    """Wall time of the baking."""
    nodes: int
    """Grid nodes over every baked field."""


class BakedGrids(NamedTuple):
    """A masked scene and library objects, each baked once (:func:`bake_grids`)."""

    scene: BakedField
    """The scene less its removal regions, in the scene field frame."""
    objects: dict[str, BakedField]
    """Library object name -> its grid, in its own field frame."""
    seconds: float
    """Wall time of the baking (NaN for grids read back from files)."""
    nodes: int
    """Grid nodes over every baked field."""


def masked_scene(composite: CompositeField) -> CompositeField:
    """The scene of ``composite`` less its removal regions, with no placed objects, evaluated
    everywhere (no culling): a grid holds the masked scene's distances, not the lower bounds that
    stand in for them deep inside a removal region (:meth:`CompositeField.scene_masked`)."""
    return CompositeField(composite.scene, [], list(composite.removals),
                          dataclasses.replace(composite.config, cull=False), info=composite.scene.info)


def placed_to_world(composite: CompositeField) -> list[np.ndarray]:
    """(4, 4) float64 per placement: its library field frame -> world metres."""
    S = composite.scene.to_world.detach().cpu().double().numpy()
    return [S @ p.mapped.matrix.detach().cpu().double().numpy() for p in composite.placements]


def bake_grids(scene: Field, objects: Mapping[str, tuple[Field, Sequence[np.ndarray]]],
               cameras: Sequence[Camera], config: BakeConfig | None = None, progress: bool = False,
               workers: int | None = None, check_nodes: Callable[[int], None] | None = None) -> BakedGrids:
    """Bake a masked scene and library objects for ``cameras``.

    Parameters
    ----------
    scene : Field
        The scene less its removal regions (:func:`masked_scene`), in the scene field frame.
    objects : mapping of name -> (Field, sequence of (4, 4) float)
        Each library field with the field frame -> world maps of the places it may stand in
        (:func:`placed_to_world`): its cell is the finest over them.
    cameras : sequence of Camera
        The views that will look (metres).
    config : BakeConfig, optional
        Defaults to ``BakeConfig()``.
    progress : bool
        Show a progress bar per baked field.
    workers : int, optional
        Fields baked at once, each on one CPU thread (:func:`regnf.core.threads.map_one_thread_each`);
        None: one per usable core. One thread per field makes the grids the same on any machine.
    check_nodes : callable, optional
        Called with the grid nodes of all the fields before any baking (a caller's disk check);
        what it raises stops the bake.

    Raises
    ------
    ValueError
        The grids would exceed ``config.max_total_nodes`` (before any baking), or an object has
        no place.
    """
    config = config or BakeConfig()
    t0 = time.perf_counter()
    names = list(objects)
    fields = [scene, *(objects[n][0] for n in names)]
    cells = [bake_cell(scene, cameras, config)]
    for n in names:
        field, places = objects[n]
        if not places:
            raise RegnfError(f"library object {n!r} has no place to be baked for")
        cells.append(min(bake_cell(field, cameras, config, to_world=W) for W in places))
    total = sum(math.prod(grid_nodes(f.bounds, c, config.coarse_stride)) for f, c in zip(fields, cells))
    _check_nodes(total, f"these {len(fields)} fields", config)  # before any baking
    if check_nodes is not None:
        check_nodes(total)
    # The largest first, so that the others fill the remaining workers around it.
    order = sorted(range(len(fields)), key=lambda i: -math.prod(grid_nodes(fields[i].bounds, cells[i])))
    baked_in_order = map_one_thread_each(lambda i: bake(fields[i], cells[i], config, progress=progress),
                                         order, workers)
    baked = dict(zip(order, baked_in_order))
    return BakedGrids(baked[0], {n: baked[k] for k, n in enumerate(names, start=1)},
                      time.perf_counter() - t0, total)


def with_grids(composite: CompositeField, scene: BakedField, objects: Sequence[BakedField]) -> CompositeField:
    """``composite`` with ``scene`` (its masked scene, baked) and ``objects`` (one grid per
    placement, in order) in place of its fields; similarities, instance ids and tints kept."""
    if len(objects) != len(composite.placements):
        raise RegnfError(f"{len(objects)} grids for {len(composite.placements)} placed objects")
    placed = [obj._replace(field=g) for obj, g in zip(composite.placed(), objects, strict=True)]
    return CompositeField(scene, placed, [], composite.config, info=composite.info)


def with_object_grids(comp: Any, selections: Mapping[str, str], grids: BakedGrids) -> CompositeField:
    """The composite of a stage whose instances show ``selections`` with ``grids`` (baked by
    :func:`bake_grids` for its masked scene and objects) in place of its fields.

    Parameters
    ----------
    comp : StageComposite
        :func:`regnf.compositor.from_stage.composite_from_scene` of the stage with those
        selections (substitute mode).
    selections : mapping of str -> str
        Instance id -> the library object it shows.
    grids : BakedGrids
        Holds a grid for every object shown.

    Raises
    ------
    ValueError
        ``grids`` lack an object shown.
    """
    name_of = {comp.instance_ids[iid]: name for iid, name in selections.items()}
    missing = sorted(set(name_of.values()) - set(grids.objects))
    if missing:
        raise RegnfError(f"the baked grids hold no {missing}: bake them for these objects again")
    return with_grids(comp.field, grids.scene, [grids.objects[name_of[k]] for k in comp.field.instance_ids])


def baked_tracing(config: SphereTracerConfig) -> SphereTracerConfig:
    """The sphere tracer's settings for a baked field: ``config`` without the distance grid.

    The grid skips empty space with one look-up where a network would be evaluated; a baked
    field's value is a look-up already, and the grid's steps only add to the steps the field's
    own distances take (docs/decisions/rendering-speed.md).
    """
    return dataclasses.replace(config, grid_resolution=0)


def is_baked(field: Field) -> bool:
    """Whether every field ``field`` reads is a grid (a baked field, or a composite of them with
    no removal regions): baking it again would change nothing."""
    if isinstance(field, BakedField):
        return True
    return (isinstance(field, CompositeField) and isinstance(field.scene, BakedField) and not len(field.removals)
            and all(isinstance(p.field, BakedField) for p in field.placements))


def bake_for_views(composite: Field, cameras: Sequence[Camera], config: BakeConfig | None = None,
                   progress: bool = False) -> BakedComposite:
    """``composite`` with its masked scene and its library fields baked for ``cameras``.

    Parameters
    ----------
    composite : Field
        A :class:`CompositeField`; any other field is baked whole. A field that is baked
        already (:func:`is_baked`) is returned as it is.
    cameras : sequence of Camera
        The views to be rendered (metres): each field's cell follows their pixel footprint
        (:func:`~regnf.render.baked_field.bake_cell`).
    config : BakeConfig, optional
        Defaults to ``BakeConfig()``.
    progress : bool
        Show a progress bar per baked field.
    """
    config = config or BakeConfig()
    t0 = time.perf_counter()
    if is_baked(composite):
        return BakedComposite(composite, 0.0, _nodes(composite))
    if not isinstance(composite, CompositeField):
        cell = bake_cell(composite, cameras, config)
        nodes = math.prod(grid_nodes(composite.bounds, cell, config.coarse_stride))
        _check_nodes(nodes, "this field", config)
        return BakedComposite(bake(composite, cell, config, progress=progress), time.perf_counter() - t0, nodes)
    # One grid per library object, shared by its instances.
    places: dict[int, tuple[Field, list[np.ndarray]]] = {}
    for p, W in zip(composite.placements, placed_to_world(composite)):
        places.setdefault(id(p.field), (p.field, []))[1].append(W)
    grids = bake_grids(masked_scene(composite), {str(k): v for k, v in places.items()}, cameras, config, progress)
    field = with_grids(composite, grids.scene, [grids.objects[str(id(p.field))] for p in composite.placements])
    return BakedComposite(field, time.perf_counter() - t0, grids.nodes)


def _check_nodes(total: int, what: str, config: BakeConfig) -> None:
    """Refuse to bake ``what`` into ``total`` grid nodes beyond ``config.max_total_nodes``."""
    if total > config.max_total_nodes:
        raise RegnfError(f"baking {what} for these views needs {total:,} grid nodes "
                         f"({16 * total / 2**30:.1f} GB), more than max_total_nodes={config.max_total_nodes:,}: "
                         "render with the sphere tracer, or take coarser cells (cell_pixels)")


def _nodes(field: Field) -> int:
    fields = [field] if isinstance(field, BakedField) else [field.scene, *(p.field for p in field.placements)]
    return sum(math.prod(f.nodes) for f in {id(f): f for f in fields}.values())
