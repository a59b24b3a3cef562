"""One variant of ``regnf generate``, as a worker makes it (:func:`render_variant`).

The driver (:mod:`regnf.datasets.generation`) sends a :class:`VariantTask` to a worker process; the worker
composes the variant from the base stage (read once per process and kept, with the fields it
loads), renders its views in a private folder, labels them, and returns the files as bytes in a
:class:`VariantOutput`, which the driver puts in place.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

from regnf.compositor.render_folder import RenderConfig
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.errors import RegnfError
from regnf.render.camera import Camera

from .bop import ModelPlan
from .data_set_formats import variant_bop_scene
from .full_masks import full_masks
from .generate_layout import STAGE_DIR, VARIANTS_DIR, variant_name
from .placement_jitter import manifest_entry
from .variant_labels import instance_boxes, write_labels
from .variation import draw_appearance, vary_views


class VariantTask(NamedTuple):
    """One variant, as sent to a worker."""

    base_stage: str
    """Absolute path of the base stage (every worker must see it)."""
    seed: int
    """The variant's seed."""
    cameras: list[Camera]
    """Its cameras, in scene metres."""
    layer_name: str
    """Name of its replacement layer (beside the base stage), recorded in transforms.json."""
    composite: StageCompositeConfig
    """Removal settings (substitute mode)."""
    render: RenderConfig
    """Renderer settings."""
    device: str
    """Torch device."""
    scratch: str | None = None
    """Folder in which the worker makes its private folder: the run's scratch folder in the
    output folder (removed by the driver, or by the next run if this one is killed); None:
    the system's temporary folder."""
    baked: str | None = None
    """Absolute path of the data set's ``baked/index.json`` (the baked renderer), or None."""
    formats: tuple[str, ...] = ("nerfstudio",)
    """The data set's formats (:data:`regnf.datasets.variant_labels.FORMATS`)."""
    appearance: tuple[float, float] = (0.0, 0.0)
    """Largest exposure change (stops) and white-balance change (fraction) of the variant."""
    frames: tuple[int, ...] | None = None
    """With capture cameras, the capture frames its cameras are (indices, one per view); None: an orbit."""
    placement: tuple[float, float] = (0.0, 0.0)
    """Largest turn (degrees) and move (metres) of each instance (:mod:`regnf.datasets.placement_jitter`)."""
    bop: ModelPlan | None = None
    """The run's BOP models when BOP is among the formats: the worker writes the variant's scene."""


class VariantOutput(NamedTuple):
    """What a worker returns: the variant's files as bytes, and what it chose."""

    seed: int
    """The variant's seed."""
    selections: dict[str, str]
    """Instance id -> library object shown."""
    instance_ids: dict[str, int]
    """Instance id -> id in the instance images."""
    files: dict[str, bytes]
    """File name -> content (views, class images, contact sheet, render.json, transforms.json, coco.json)."""
    seconds: float
    """Time the worker spent (loading, composing, rendering)."""
    boxes: dict[str, Any]
    """Instance id -> its 3D box (:func:`regnf.datasets.variant_labels.instance_boxes`)."""
    appearance: dict[str, Any]
    """The camera appearance drawn for the variant (:mod:`regnf.datasets.variation`)."""
    frames: tuple[int, ...] | None = None
    """The capture frames of its views (:attr:`VariantTask.frames`); None: an orbit."""
    placement: dict[str, Any] | None = None
    """Instance id -> its placement jitter (:func:`regnf.datasets.placement_jitter.manifest_entry`); None:
    no jitter asked for."""
    bop_files: dict[str, bytes] | None = None
    """Its BOP scene, relative path -> content (:func:`regnf.datasets.data_set_formats.variant_bop_scene`);
    None: BOP not asked for."""



# Per worker process: the stage as read and its loaded fields, kept across the variants it runs.
_WORKER_CACHE: dict[str, Any] = {}


def warm_worker(base_stage: str) -> None:
    """Start a worker before its first variant: import what :func:`render_variant` needs and
    read the base stage into the worker's cache."""
    from regnf.compositor import from_stage, nerfstudio, render_folder, replace  # noqa: F401

    from . import data_set_grids  # noqa: F401

    _read_base(Path(base_stage))


def _read_base(base: Path) -> Any:
    """The stage ``base`` as read (and its instances' original objects), kept in the worker's
    cache while the file is unchanged."""
    from regnf.scene_graph import original_selections, read_stage

    stamp = (str(base), base.stat().st_mtime_ns)
    if _WORKER_CACHE.get("stamp") != stamp:
        _WORKER_CACHE.clear()
        scene = read_stage(base)
        _WORKER_CACHE.update(stamp=stamp, scene=scene, originals=original_selections(base, scene), fields={})
    return _WORKER_CACHE["scene"]


def render_variant(task: VariantTask) -> VariantOutput:
    """Make one variant in a private temporary folder and return its files (runs in a worker)."""
    from regnf.compositor.from_stage import composite_from_scene
    from regnf.compositor.nerfstudio import transforms_json
    from regnf.compositor.render_folder import render_views
    from regnf.compositor.replace import pick_replacements, swapped

    t0 = time.perf_counter()
    base = Path(task.base_stage)
    scene = _read_base(base)
    selections = pick_replacements(scene, task.seed)
    comp = composite_from_scene(swapped(scene, selections), _WORKER_CACHE["originals"], base,
                                dataclasses.replace(task.composite, mode="substitute"), task.device,
                                loaded=_WORKER_CACHE["fields"])
    placed = None
    if any(task.placement):
        comp, placed = _jittered(task, scene, selections, comp)
    shown = {iid: inst.library_name for iid, inst in comp.scene.instances.items()}
    if shown != selections:
        raise RuntimeError(f"the composite shows {shown}, expected {selections}")
    field = comp.field
    if task.baked is not None:
        field = _with_data_set_grids(comp, selections, Path(task.baked), task.device)
    rel_layer = f"../../{STAGE_DIR}/{task.layer_name}"
    # Capture cameras: the frames the views are, in render.json and transforms.json too.
    shot = {} if task.frames is None else {"capture_frames": list(task.frames)}
    metadata = {"stage": rel_layer, "mode": "substitute", "seed": task.seed, "selections": selections,
                "instance_ids": comp.instance_ids, **shot}
    with tempfile.TemporaryDirectory(prefix=f"{variant_name(task.seed)}-", dir=task.scratch) as tmp:
        report = render_views(field, task.cameras, tmp, task.render, metadata)
        look = draw_appearance(task.seed, *task.appearance)
        vary_views(Path(tmp), len(task.cameras), look, task.render.sheet_columns, task.render.sheet_tile_width)
        if "nerfstudio" in task.formats:
            extra = {"seed": task.seed, "stage": rel_layer, "selections": selections,
                     "instance_ids": comp.instance_ids,
                     "instance_png": "uint16 instance id, 0 background and scene", "depth_unit_scale_factor": 1e-3,
                     **shot}
            tj = transforms_json(task.cameras, report.views, extra)
            (Path(tmp) / "transforms.json").write_text(json.dumps(tj, indent=2) + "\n")
        write_labels(Path(tmp), len(task.cameras), scene, selections, comp.instance_ids,
                     f"{VARIANTS_DIR}/{variant_name(task.seed)}", task.formats)
        bop_files = None
        if task.bop is not None:
            from regnf.compositor.baked_composite import baked_tracing

            sphere = baked_tracing(task.render.sphere) if task.baked is not None else task.render.sphere
            poses = {name: inst.object_to_scene for name, inst in comp.scene.instances.items()}
            bop_files = variant_bop_scene(Path(tmp), task.bop, selections, comp.instance_ids, poses,
                                          full_masks(Path(tmp), field, task.cameras, sphere))
        # Hidden entries are bookkeeping (the render folder's lock), not the variant's files.
        files = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir())
                 if p.is_file() and not p.name.startswith(".")}
    return VariantOutput(task.seed, selections, comp.instance_ids, files, time.perf_counter() - t0,
                         instance_boxes(comp.scene, selections, comp.instance_ids),
                         {"exposure_stops": look.stops, "white_balance": list(look.gains)}, frames=task.frames,
                         placement=None if placed is None else manifest_entry(placed), bop_files=bop_files)


def _jittered(task: VariantTask, scene: Any, selections: dict[str, str], comp: Any) -> tuple[Any, dict[str, Any]]:
    """The variant's composite ``comp`` (every instance where it was captured) with its instances
    jittered (:mod:`regnf.datasets.placement_jitter`), and their placements. The original objects stay
    removed where they were captured."""
    from regnf.compositor.from_stage import composite_from_scene

    from .placement_jitter import collision_test, draw_placements, moved_scene

    test = collision_test(comp.field, {i: scene.library[name].proxy for i, name in selections.items()},
                          comp.instance_ids)
    placed = draw_placements(task.seed, {i: r.object_to_scene for i, r in comp.scene.instances.items()},
                             *task.placement, test)
    moved = composite_from_scene(moved_scene(comp.scene, placed), _WORKER_CACHE["originals"], Path(task.base_stage),
                                 dataclasses.replace(task.composite, mode="substitute"), task.device,
                                 loaded=_WORKER_CACHE["fields"],
                                 removal_poses={i: r.object_to_scene for i, r in scene.instances.items()})
    return moved, placed


def _with_data_set_grids(comp: Any, selections: dict[str, str], index: Path, device: str) -> Any:
    """The variant's composite on the data set's grids, loaded once per worker process."""
    from regnf.compositor.baked_composite import with_object_grids

    from .data_set_grids import load_data_set_grids

    stamp = (str(index), index.stat().st_mtime_ns, device)
    if _WORKER_CACHE.get("grids_stamp") != stamp:
        _WORKER_CACHE.pop("grids", None)  # the old grids go before the new ones come
        _WORKER_CACHE.update(grids=load_data_set_grids(index, device), grids_stamp=stamp)
    try:
        return with_object_grids(comp, selections, _WORKER_CACHE["grids"])
    except ValueError as exc:
        raise RegnfError(f"{index}: {exc} (remove it to bake them again)") from None
