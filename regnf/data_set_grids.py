"""The baked grids of a data set: baked once by ``regnf generate``, read by every variant.

``out/baked/`` holds ``scene.safetensors`` (the scene less its removal regions: every
instance is removed in every variant, so this is the same for all of them), one
``object_<k>.safetensors`` per library object a variant may show, and ``index.json``, written
last: the data set's ``config_key``, each file with its SHA-256 and the grid nodes in all (no
timings: like every file of the data set but ``render.json``, it is the same on every run). The index is what makes the grids complete; a rerun keeps them when it names this
data set's key and every file still has its digest, and bakes them again otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from regnf.compositor.baked_composite import (
    BakedGrids,
    bake_grids,
    masked_scene,
    placed_to_world,
    with_grids,
)
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.atomic_io import write_json
from regnf.neural_fields.baked_field import BakeConfig, BakedField
from regnf.neural_fields.baked_io import load_baked, save_baked
from regnf.neural_fields.camera import Camera

from .manifest import sha256_file

INDEX = "index.json"
"""The record of the grids, written after them."""
SCENE_FILE = "scene.safetensors"
"""The scene less its removal regions."""


def bake_for_data_set(base: Path, folder: Path, key: str, cameras: Sequence[Camera], bake: BakeConfig,
                      composite: StageCompositeConfig, device: str = "cpu",
                      progress: bool = False) -> tuple[Path, float]:
    """The grids of the data set whose base stage is ``base``, in ``folder``: (its index, the
    seconds spent baking, 0 when the grids were kept).

    Kept as they are when ``folder``'s index names ``key`` and every file checks out; otherwise
    baked (:func:`regnf.compositor.baked_composite.bake_grids`, one CPU thread per field) and
    written, each file atomically and the index last. The caller holds the data set folder's lock.

    Parameters
    ----------
    base : Path
        The data set's base stage.
    folder : Path
        ``out/baked``.
    key : str
        The data set's config_key.
    cameras : sequence of Camera
        The orbit the variants turn (its pixel footprint chooses the cells).
    bake : BakeConfig
    composite : StageCompositeConfig
        Removal settings (substitute mode).
    device : str
    progress : bool
        Show a progress bar per baked field.
    """
    from regnf.compositor.from_stage import composite_from_scene
    from regnf.compositor.replace import replacement_candidates, swapped
    from regnf.scene_graph import original_selections, read_stage

    index = folder / INDEX
    if _index_checks_out(index, key):
        return index, 0.0
    scene = read_stage(base)
    originals = original_selections(base, scene)
    config = dataclasses.replace(composite, mode="substitute")
    loaded: dict = {}
    comp = composite_from_scene(scene, originals, base, config, device, loaded=loaded)
    where = replacement_candidates(scene)
    objects: dict[str, tuple[Any, list[np.ndarray]]] = {}
    for name in sorted({n for names in where.values() for n in names}):
        # Every instance that may show it, showing it: its placements there give its places.
        at = {iid: name for iid, names in where.items() if name in names}
        placed = composite_from_scene(swapped(scene, at), originals, base, config, device, loaded=loaded)
        k_of = placed.instance_ids
        Ws = placed_to_world(placed.field)
        places = [Ws[i] for i, k in enumerate(placed.field.instance_ids)
                  if any(k_of[iid] == k for iid in at)]
        field = next(p.field for p, k in zip(placed.field.placements, placed.field.instance_ids)
                     if any(k_of[iid] == k for iid in at))
        objects[name] = (field, places)
    grids = bake_grids(masked_scene(comp.field), objects, cameras, bake, progress)
    folder.mkdir(parents=True, exist_ok=True)
    # An old index stays until the new one replaces it: if this run is killed in between, the
    # files it rewrote no longer match its digests (and the next run bakes again), unless they
    # are the very bytes it records.
    files = {"scene": _saved(grids.scene, folder / SCENE_FILE)}
    names = {}
    for k, name in enumerate(sorted(grids.objects)):
        names[name] = _saved(grids.objects[name], folder / f"object_{k}.safetensors")
    write_json(index, {"config_key": key, "scene": files["scene"], "objects": names, "nodes": grids.nodes})
    return index, grids.seconds


def _saved(grid: BakedField, path: Path) -> dict[str, str]:
    save_baked(grid, path)
    return {"file": path.name, "sha256": sha256_file(path)}


def _entries(record: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [record["scene"], *record["objects"].values()]


def _index_checks_out(index: Path, key: str) -> bool:
    """Whether ``index`` records grids of ``key`` whose files all have their digests."""
    try:
        record = json.loads(index.read_text(encoding="utf-8"))
        if record.get("config_key") != key:
            return False
        for entry in _entries(record):
            name = entry["file"]
            if name != Path(name).name or name.startswith(".") or not name.endswith(".safetensors"):
                return False
            path = index.parent / name
            if not path.is_file() or sha256_file(path) != entry["sha256"]:
                return False
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, AttributeError):
        return False
    return True


def load_data_set_grids(index: str | os.PathLike, device: str = "cpu") -> BakedGrids:
    """The grids that ``index`` records (as :func:`bake_for_data_set` wrote them).

    Raises
    ------
    ValueError
        The index is unreadable or malformed, or a grid file is (naming the file).
    """
    index = Path(index)
    try:
        record = json.loads(index.read_text(encoding="utf-8"))
        scene_file = record["scene"]["file"]
        object_files = {str(n): e["file"] for n, e in record["objects"].items()}
        nodes = int(record["nodes"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{index}: not a record of baked grids ({type(exc).__name__}: {exc})") from None
    for name in (scene_file, *object_files.values()):
        if not isinstance(name, str) or name != Path(name).name or name.startswith("."):
            raise ValueError(f"{index}: grid file {name!r} is not a plain file name in {index.parent}")
    return BakedGrids(load_baked(index.parent / scene_file, device),
                      {n: load_baked(index.parent / f, device) for n, f in object_files.items()},
                      float("nan"), nodes)


def with_data_set_grids(comp: Any, selections: Mapping[str, str], grids: BakedGrids) -> Any:
    """The composite of a variant (a :class:`regnf.compositor.from_stage.StageComposite` whose
    instances show ``selections``) with the data set's grids in place of its fields."""
    name_of = {comp.instance_ids[iid]: name for iid, name in selections.items()}
    missing = sorted(set(name_of.values()) - set(grids.objects))
    if missing:
        raise ValueError(f"the data set's baked grids hold no {missing}; remove {INDEX} to bake them again")
    return with_grids(comp.field, grids.scene, [grids.objects[name_of[k]] for k in comp.field.instance_ids])
