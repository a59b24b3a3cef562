"""Instance replacement as training data: swap objects at random, render, write transforms.json.

For a seed, every instance gets a random library object of its own class (another one when
the class has another; an instance whose class has only its own object keeps it). The swap
is a replacement layer (:func:`regnf.scene_graph.make_replacement_layer`) at ``out/replacement.usda``;
the substitute composite of that layer is rendered as by :func:`regnf.compositor.render_folder.render_views`
and described by a nerfstudio ``transforms.json``.

A replacement layer must lie beside its base stage (its asset paths are relative). When
``out`` is not the stage's folder, the base stage is therefore first exported into ``out``
(:func:`regnf.scene_graph.export_stage`; a .usdz package is unpacked), so that the output folder
is a complete stage plus its renders.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from regnf.core.atomic_io import write_json
from regnf.core.errors import RegnfError
from regnf.render.camera import Camera
from regnf.scene_graph import (
    ComposedScene,
    StageError,
    export_stage,
    make_replacement_layer,
    original_selections,
    read_stage,
)

from .baked_composite import BakedGrids, with_object_grids
from .from_stage import composite_from_scene, composite_from_stage
from .nerfstudio import transforms_json
from .render_folder import RenderConfig, RenderReport, check_cameras, check_sequence, render_views
from .size_change import check_swap_sizes
from .stage_config import StageCompositeConfig

LAYER_NAME = "replacement.usda"
"""The replacement layer written into the output folder."""
TRANSFORMS_NAME = "transforms.json"
"""nerfstudio's camera file written into the output folder."""


@dataclass(frozen=True)
class ReplaceConfig:
    """Settings of :func:`replace_and_render`."""

    composite: StageCompositeConfig = field(default_factory=StageCompositeConfig)
    """Removal and tint settings; the mode is always ``substitute``."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """Renderer and output settings."""
    device: str = "cpu"
    """Torch device the fields are loaded on."""
    allow_size_change: bool = False
    """Allow swaps that change an instance's size by more than :data:`~regnf.compositor.size_change.SIZE_CHANGE_LIMIT` times."""


class ReplacementResult(NamedTuple):
    """What :func:`replace_and_render` made."""

    layer: Path
    """``out/replacement.usda``: the variant selections over the base stage."""
    base_stage: Path
    """The stage the layer sits over (the input, or its copy in ``out``)."""
    selections: dict[str, str]
    """Instance id -> library object now shown."""
    instance_ids: dict[str, int]
    """Instance id -> id in the instance images."""
    render: RenderReport
    """The rendered views."""
    transforms: Path
    """``out/transforms.json``."""


def replacement_candidates(scene: ComposedScene) -> dict[str, list[str]]:
    """Instance id -> the library objects :func:`pick_replacements` chooses among, sorted by
    name: the OTHER objects of its class, or its own object if there is none."""
    classes = scene.classes()
    out = {}
    for iid in sorted(scene.instances):  # a handful of instances
        current = scene.instances[iid].library_name
        label = scene.library[current].label
        out[iid] = [n for n in classes[label] if n != current] or [current]
    return out


def pick_replacements(scene: ComposedScene, seed: int) -> dict[str, str]:
    """Instance id -> a random library object of the same class (``numpy`` Generator(seed)).

    Instances are visited in sorted id order and the candidates are sorted by name, so the
    choice depends on the seed and the stage only. An instance picks among the OTHER objects
    of its class; if there is none it keeps its own (:func:`replacement_candidates`).
    """
    rng = np.random.default_rng(seed)
    return {iid: others[int(rng.integers(len(others)))]
            for iid, others in replacement_candidates(scene).items()}


def base_in(stage: Path, out: Path, allow_outside: bool = False) -> Path:
    """The base stage for a layer in ``out``: ``stage`` itself, or a copy of it exported there.

    A .usdz package is always unpacked into ``out`` (a layer beside a package cannot reach the
    library layers inside it). With ``allow_outside``, a stage whose asset paths leave its
    folder is always exported: the copy in ``out`` is self-contained, and the layer over it
    needs no exception.
    """
    if stage.suffix == ".usdz":
        return export_stage(stage, out / f"{stage.stem}.usda", allow_outside=allow_outside)
    if stage.parent == out and not allow_outside:
        return stage
    # Under another name where the layer's name is taken, or beside the stage itself (with
    # allow_outside: a self-contained copy of it).
    clash = stage.name == LAYER_NAME or stage.parent == out
    name = f"base_{stage.name}" if clash else stage.name
    return export_stage(stage, out / name, allow_outside=allow_outside)


def swapped(scene: ComposedScene, selections: dict[str, str]) -> ComposedScene:
    """``scene`` with each instance showing its selection (in memory; registrations kept)."""
    instances = {
        iid: dataclasses.replace(inst, library_name=selections.get(iid, inst.library_name))
        for iid, inst in scene.instances.items()
    }
    return dataclasses.replace(scene, instances=instances)


def replace_and_render(
    stage: str | os.PathLike,
    seed: int,
    out: str | os.PathLike,
    cameras: Sequence[Camera],
    config: ReplaceConfig = ReplaceConfig(),
    allow_outside: bool = False,
    grids: BakedGrids | None = None,
) -> ReplacementResult:
    """Swap every instance at random (same class), render the result, write training data.

    The swapped composite is built in memory first and every camera checked against it, so
    that a camera inside matter is refused before anything is written; if rendering fails
    later, the layer is removed again (an exported base stage stays: it is complete).

    Parameters
    ----------
    stage : str or PathLike
        A regnf stage, replacement layer or .usdz package.
    seed : int
        Seed of the choices; the same seed gives the same files (``render.json`` aside, whose
        timings vary).
    out : str or PathLike
        Output folder: ``replacement.usda`` (over the stage, exported beside it if needed),
        the views, ``contact_sheet.png``, the sequence if ``config.render`` asks for one,
        ``render.json`` and ``transforms.json``.
    cameras : sequence of Camera
        Posed in scene metres.
    config : ReplaceConfig
    allow_outside : bool
        Read a stage whose asset paths leave its folder (see :func:`regnf.scene_graph.read_stage`);
        its base is then exported into ``out``, self-contained.
    grids : BakedGrids, optional
        The stage's masked scene and library objects baked once
        (:func:`regnf.compositor.baked_composite.bake_grids`, with ``config.composite``'s
        removal settings): the variant renders on them with the baked renderer, whatever
        ``config.render.renderer`` says, instead of baking its own (for several seeds of one
        stage). Every object a seed may pick must have its grid.

    Raises
    ------
    StageError
        The stage cannot be read or the layer cannot be written (the message names the file).
    ValueError
        No camera, a camera inside matter, an existing layer in ``out`` (unless overwriting),
        a sequence of views of different sizes, grids without an object the seed picks, a
        swap that changes an instance's size too much
        (:class:`~regnf.compositor.size_change.SizeChangeError`, unless
        ``config.allow_size_change``).
    regnf.compositor.sequence_io.SequenceBackendError
        An MP4 sequence without its package (an ``ImportError``); nothing is written then.
    """
    t0 = time.perf_counter()
    src = Path(stage).absolute()
    dest = Path(out).absolute()
    if (dest / LAYER_NAME).exists() and not config.render.overwrite:
        raise RegnfError(f"{dest} already holds {LAYER_NAME}; overwrite it explicitly")
    if src == dest / LAYER_NAME:
        raise RegnfError(f"the stage is {LAYER_NAME} of the output folder itself; choose another output folder")
    if len(cameras) == 0:
        raise RegnfError("nothing to render: no camera")
    check_sequence(cameras, config.render)
    composite_cfg = dataclasses.replace(config.composite, mode="substitute")
    device = torch.device(config.device)
    scene = read_stage(src, allow_outside=allow_outside)
    selections = pick_replacements(scene, seed)
    if not config.allow_size_change:
        check_swap_sizes(scene, {iid: [name] for iid, name in selections.items()}, src)
    if grids is not None and set(selections.values()) - set(grids.objects):
        raise RegnfError(f"the baked grids hold no {sorted(set(selections.values()) - set(grids.objects))}, "
                         f"which seed {seed} shows: bake them for every object a seed may pick")
    preview = composite_from_scene(swapped(scene, selections),
                                   original_selections(src, scene, allow_outside=allow_outside), src,
                                   composite_cfg, device)
    check_cameras(preview.field, cameras)
    del preview
    dest.mkdir(parents=True, exist_ok=True)
    base = base_in(src, dest, allow_outside)
    layer = make_replacement_layer(base, selections, dest / LAYER_NAME)
    try:
        comp = composite_from_stage(layer, composite_cfg, device)
        shown = {iid: inst.library_name for iid, inst in comp.scene.instances.items()}
        if shown != selections:
            raise StageError(layer, "/World/Instances", f"selects {shown}, expected {selections}")
        metadata = {
            "stage": str(layer),
            "base_stage": str(base),
            "source_stage": str(src),
            "mode": "substitute",
            "seed": int(seed),
            "selections": selections,
            "instance_ids": comp.instance_ids,
            "composite_config": dataclasses.asdict(composite_cfg),
            "load_seconds": time.perf_counter() - t0,
        }
        field, render = comp.field, config.render
        if grids is not None:
            field = with_object_grids(comp, selections, grids)
            render = dataclasses.replace(render, renderer="baked")
        report = render_views(field, cameras, dest, render, metadata)
        extra = {"seed": int(seed), "stage": LAYER_NAME, "selections": selections,
                 "instance_ids": comp.instance_ids,
                 "instance_png": "uint16 instance id, 0 background and scene", "depth_unit_scale_factor": 1e-3}
        write_json(dest / TRANSFORMS_NAME, transforms_json(cameras, report.views, extra))
    except BaseException:
        layer.unlink(missing_ok=True)
        raise
    return ReplacementResult(layer, base, selections, comp.instance_ids, report, dest / TRANSFORMS_NAME)
