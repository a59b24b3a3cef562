"""Instance replacement: a small layer of variant selections over a base stage.

The layer sublayers the base stage and, per replaced instance, overrides the slot's
variant selection; nothing else. Because every instance of a class references the same
slot asset, instances that select the same object still share one prototype (authoring a
VariantSet per instance would give each its own). Canonical object frames (base centred at
the origin, +Z up, +X forward) make the new object stand on the floor with the old heading.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from pxr import Sdf

from . import layout as L
from .errors import StageError
from .locking import stage_lock
from .model import ComposedScene
from .transaction import file_transaction
from .usd_read import read_stage, regnf_data, replacement_base, root_layer_of


def make_replacement_layer(
    base_stage_path: str | os.PathLike,
    selections: Mapping[str, str],
    out_path: str | os.PathLike,
    force: bool = False,
    allow_outside: bool = False,
) -> Path:
    """Write a layer over ``base_stage_path`` that swaps instances' library objects.

    Parameters
    ----------
    base_stage_path : str or PathLike
        A regnf stage.
    selections : mapping
        Instance id -> library name to show instead.
    out_path : str or PathLike
        The layer to write (.usda or .usdc), in the base stage's folder (its relative asset
        paths are the base's).
    force : bool
        Allow a swap to an object of a different class (the instance then references that
        class's slot).
    allow_outside : bool
        Read a base stage whose asset paths leave its folder (see :func:`read_stage`).

    Returns
    -------
    Path
        ``out_path``, readable by :func:`regnf.scene_graph.read_stage`.

    Raises
    ------
    StageError
        Unknown instance or library object, a swap across classes (unless forced), an output
        outside the base stage's folder; nothing is written then.
    regnf.core.file_lock.LockBusy
        Another process kept the stage's folder locked for too long.

    Notes
    -----
    The layer is written into the base stage's folder, so the folder's lock is held from
    before the base is read until the layer is in place: an edit of the base meanwhile would
    otherwise leave a layer made for instances the base no longer has.
    """
    base = Path(base_stage_path).absolute()
    out = Path(out_path).absolute()
    if out.parent != base.parent:
        raise StageError(out, "/", f"a replacement layer must lie beside its base stage in {base.parent} "
                         "(its relative asset paths would otherwise escape the stage's folder)")
    if out.suffix not in (".usda", ".usdc"):
        raise StageError(out, "/", "a replacement layer must end in .usda or .usdc")
    if out == base:
        raise StageError(out, "/", "the replacement layer cannot overwrite its base stage")
    bad = [k for k, v in selections.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise StageError(base, L.INSTANCES, f"selections must map instance ids to library names (strings), got {bad}")
    with stage_lock(base):  # the folder of both: the layer lies beside its base
        scene = read_stage(base, allow_outside=allow_outside)
        layer = _layer(base, scene, selections, out.suffix, force)
        with file_transaction() as tx:
            layer.Export(str(tx.temp_path(out)))
    return out


def _layer(base: Path, scene: ComposedScene, selections: Mapping[str, str], suffix: str, force: bool) -> Sdf.Layer:
    """The anonymous replacement layer over ``base`` (read as ``scene``); see the caller."""
    layer = Sdf.Layer.CreateAnonymous(suffix)
    layer.pseudoRoot.SetInfo("upAxis", "Z")
    layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
    layer.defaultPrim = "World"
    base_layer = root_layer_of(base)
    data = dict(regnf_data(base_layer, str(base)))
    data["replacementOf"] = "./" + base.name
    data["selections"] = dict(selections)
    layer.customLayerData = {"regnf": data}
    layer.subLayerPaths.append("./" + base.name)
    world = Sdf.PrimSpec(layer, "World", Sdf.SpecifierOver, "")
    parent = Sdf.PrimSpec(world, "Instances", Sdf.SpecifierOver, "")
    for iid, name in selections.items():
        prim = L.instance_path(iid)
        if iid not in scene.instances:
            raise StageError(base, prim, f"no such instance (instances: {sorted(scene.instances)})")
        if name not in scene.library:
            raise StageError(base, prim, f"library object {name!r} is not in the stage's library {sorted(scene.library)}")
        old = scene.library[scene.instances[iid].library_name].label
        new = scene.library[name].label
        spec = Sdf.PrimSpec(parent, iid, Sdf.SpecifierOver, "")
        if old != new:
            if not force:
                raise StageError(base, prim, f"cannot replace a {old} by {name!r}, a {new} (force to allow)")
            # The other class's slot replaces the reference (an explicit list is the strongest).
            spec.referenceList.explicitItems = [Sdf.Reference("./" + L.slot_layer(new))]
        spec.variantSelections[L.VARIANT_SET] = name
    return layer


MAX_LAYER_DEPTH = 16
"""Longest chain of replacement layers followed to find an instance's original object."""


def original_selections(stage_path: str | os.PathLike, scene: ComposedScene, depth: int = 0,
                        allow_outside: bool = False) -> dict[str, str]:
    """Instance id -> the library object that was REGISTERED (the one to remove).

    The registration provenance's library name when recorded; otherwise, for a replacement
    layer, the selection of the stage beneath it (recursively); otherwise the selection.

    Parameters
    ----------
    stage_path : str or PathLike
        The stage ``scene`` was read from.
    scene : ComposedScene
    depth : int
        Replacement layers followed so far (at most :data:`MAX_LAYER_DEPTH`).
    allow_outside : bool
        Follow a ``replacementOf`` outside the layer's folder (refused by default, before the
        base is opened).
    """
    below = _beneath(stage_path, depth, allow_outside, original_selections)
    out = {}
    for iid, inst in scene.instances.items():
        reg = inst.registration
        out[iid] = reg.library_name if reg is not None and reg.library_name else below.get(iid, inst.library_name)
    return out


def original_poses(stage_path: str | os.PathLike, scene: ComposedScene, depth: int = 0,
                   allow_outside: bool = False) -> dict[str, np.ndarray]:
    """Instance id -> (4, 4) ``object_to_scene`` of the stage beneath every replacement layer.

    The original object is removed where that stage places it: a layer that also moves the
    shown object (``regnf generate``'s placement jitter) leaves the removal where the captured
    object was. For a plain stage, or layers that move nothing, these are ``scene``'s own.
    Parameters as :func:`original_selections`.
    """
    below = _beneath(stage_path, depth, allow_outside, original_poses)
    return {iid: below.get(iid, inst.object_to_scene) for iid, inst in scene.instances.items()}


def _beneath(stage_path: str | os.PathLike, depth: int, allow_outside: bool,
             walk: Callable[[Path, ComposedScene, int, bool], dict]) -> dict:
    """``walk`` of the stage a replacement layer is over ({} for a plain stage)."""
    path = Path(stage_path).absolute()
    base = replacement_base(path, allow_outside)
    if base is None:
        return {}
    if depth >= MAX_LAYER_DEPTH:
        raise StageError(path, "/", f"more than {MAX_LAYER_DEPTH} nested replacement layers")
    return walk(base, read_stage(base, check_checkpoints=False, allow_outside=allow_outside), depth + 1, allow_outside)
