"""A composite field from a USD stage: the scene field, minus and plus its instances.

Works on everything :func:`regnf.scene_graph.read_stage` reads: .usda / .usdc stages, replacement
layers (an instance then SHOWS the newly selected object but the ORIGINAL one, the object
that was registered, is removed, where the stage beneath the layers places it: a layer of
``regnf generate`` may move the shown object, :func:`original_poses`) and .usdz packages
(checkpoints carried inside). Frames and removal regions are those of
:mod:`regnf.compositor.substitution`.

Every stage, and every base stage a replacement layer names (``replacementOf``), is read
inside its folder's trust boundary (:mod:`regnf.scene_graph.boundary`): a path that leaves the
folder is refused before the file it names is opened, unless ``allow_outside``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, MutableMapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.scene_graph import (
    INSTANCES_PRIM,
    SCENE_PRIM,
    ComposedScene,
    RegistrationProvenance,
    StageError,
    instance_path,
    load_record_field,
    original_poses,
    original_selections,
    read_stage,
)

from .composite_field import CompositeField
from .stage_config import DEFAULT_STAGE_COMPOSITE, StageCompositeConfig
from .substitution import SubstitutedInstance, build_composite, check_z_up


class StageComposite(NamedTuple):
    """A stage turned into one field."""

    field: CompositeField
    """The composite, in the scene field frame (the scene's ``to_world``)."""
    scene: ComposedScene
    """The stage as read."""
    instance_ids: dict[str, int]
    """Stage instance id -> integer id >= 1 in renders (empty in ``scene`` mode)."""


def composite_from_stage(
    stage_path: str | os.PathLike,
    config: StageCompositeConfig = DEFAULT_STAGE_COMPOSITE,
    device: torch.device | str = "cpu",
    allow_outside: bool = False,
) -> StageComposite:
    """Load a stage's fields and compose them (see the module).

    Parameters
    ----------
    stage_path : str or PathLike
        A regnf stage, replacement layer or .usdz package.
    config : StageCompositeConfig
    device : torch.device or str
        Where every field is loaded.
    allow_outside : bool
        Accept asset paths and base stages outside the stage's folder (see
        :func:`regnf.scene_graph.read_stage`); refused by default.

    Returns
    -------
    StageComposite
        Instance ids are numbered 1, 2, ... in the stage's instance order.

    Raises
    ------
    StageError
        Naming the stage (or checkpoint) and prim: anything :func:`read_stage` refuses, a
        checkpoint that does not load, a recorded ``to_world`` that disagrees with its
        checkpoint, a scene field frame that is not +Z up, an unusable proposal box.
    """
    path = Path(stage_path).absolute()
    scene = read_stage(path, allow_outside=allow_outside)
    if config.mode != "substitute":
        return composite_from_scene(scene, {}, path, config, device)
    originals = original_selections(path, scene, allow_outside=allow_outside)
    return composite_from_scene(scene, originals, path, config, device,
                                removal_poses=original_poses(path, scene, allow_outside=allow_outside))


def composite_from_scene(
    scene: ComposedScene,
    originals: dict[str, str],
    stage_path: str | os.PathLike,
    config: StageCompositeConfig = DEFAULT_STAGE_COMPOSITE,
    device: torch.device | str = "cpu",
    loaded: MutableMapping[str, Field] | None = None,
    removal_poses: Mapping[str, np.ndarray] | None = None,
) -> StageComposite:
    """:func:`composite_from_stage` of a stage already read (or changed in memory).

    Parameters
    ----------
    scene : ComposedScene
        What the stage holds; each instance shows its ``library_name``.
    originals : dict
        Instance id -> the library object to remove (see :func:`original_selections`);
        unused in ``scene`` mode.
    stage_path : str or PathLike
        The stage ``scene`` comes from, named in errors.
    config : StageCompositeConfig
    device : torch.device or str
    loaded : mutable mapping, optional
        Fields already loaded, by checkpoint identifier; new ones are added. A worker that
        composes many variants of one stage loads each checkpoint once (the composite only
        reads its fields).
    removal_poses : mapping, optional
        Instance id -> (4, 4) ``object_to_scene`` where its original object is removed, when
        the shown object stands elsewhere (:func:`original_poses`); an instance not named is
        removed where it stands.
    """
    path = Path(stage_path).absolute()
    scene_field = load_record_field(path, SCENE_PRIM, scene.scene, device, loaded)
    if config.mode == "scene":
        return StageComposite(build_composite(scene_field, [], config), scene, {})
    try:
        check_z_up(scene.scene.to_world, f"scene field {scene.scene.name!r}")
    except ValueError as exc:
        raise StageError(path, SCENE_PRIM, str(exc)) from exc
    cache: dict[str, Field] = {}
    specs, ids = [], {}
    for k, (iid, inst) in enumerate(scene.instances.items(), start=1):
        where = instance_path(iid)
        original = originals.get(iid, inst.library_name)
        for name in (original, inst.library_name):
            if name not in scene.library:
                raise StageError(path, where, f"library object {name!r} is not in the stage's library "
                                 f"{sorted(scene.library)}")
        load = _loader(path, where, scene, cache, device, loaded)
        specs.append(SubstitutedInstance(
            instance_id=k,
            shown=load(inst.library_name),
            original=load(original),
            object_to_scene=inst.object_to_scene,
            proposal=_proposal(path, where, inst.registration),
            name=iid,
            removal_to_scene=None if removal_poses is None else removal_poses.get(iid),
        ))
        ids[iid] = k
    try:
        field = build_composite(scene_field, specs, config)
    except ValueError as exc:
        raise StageError(path, INSTANCES_PRIM, str(exc)) from exc
    return StageComposite(field, scene, ids)


def _loader(
    stage: Path, where: str, scene: ComposedScene, cache: dict[str, Field], device: torch.device | str,
    loaded: MutableMapping[str, Field] | None = None,
) -> Callable[[str], Field]:
    """A function loading library objects by name, each once (shared by its instances)."""

    def load(name: str) -> Field:
        if name not in cache:
            cache[name] = load_record_field(stage, f"{where} (library object {name!r})", scene.library[name], device, loaded)
        return cache[name]

    return load


def _proposal(stage: Path, where: str, reg: RegistrationProvenance | None) -> OrientedBox | None:
    """The registration's proposal box (scene field frame), if recorded."""
    if reg is None or reg.proposal_center is None or reg.proposal_half_extents is None:
        return None
    try:
        return OrientedBox(reg.proposal_center, reg.proposal_half_extents, reg.proposal_rotation)
    except ValueError as exc:
        raise StageError(stage, where, f"unusable registration proposal box: {exc}") from exc
