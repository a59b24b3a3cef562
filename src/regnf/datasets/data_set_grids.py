"""The baked grids of a data set: baked once by ``regnf generate``, read by every variant.

``regnf demo`` keeps the grids of its stage the same way in the cache
(:func:`cached_stage_grids`), keyed by everything they are made from, so that a second run
reads them instead of baking again; they hold each instance's own object too (its
substitution), and their index says so (``"substitution": true``).

``out/baked/`` holds ``scene.safetensors`` (the scene less its removal regions: every
instance is removed in every variant, so this is the same for all of them), one
``object_<k>.safetensors`` per library object a variant may show, and ``index.json``, written
last: the data set's ``config_key``, each file with its SHA-256 and the grid nodes in all (no
timings: like every file of the data set but ``render.json``, it is the same on every run). The index is what makes the grids complete; a rerun keeps them when it names this
data set's key and every file still has its digest, and bakes them again otherwise.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import hashlib
import json
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from regnf.compositor.baked_composite import BakedGrids, bake_grids, masked_scene, placed_to_world
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.atomic_io import write_json
from regnf.core.errors import RegnfError
from regnf.core.file_lock import LockBusy, folder_lock
from regnf.core.preflight import JsonInputError, check_free_space, read_json_input
from regnf.core.threads import usable_cores
from regnf.render.baked_field import BakeConfig, BakedField
from regnf.render.baked_io import BYTES_PER_NODE, load_baked, save_baked
from regnf.render.camera import Camera

from .manifest import sha256_file

INDEX = "index.json"
"""The record of the grids, written after them."""
SCENE_FILE = "scene.safetensors"
"""The scene less its removal regions."""


def bake_for_data_set(base: Path, folder: Path, key: str, cameras: Sequence[Camera], bake: BakeConfig,
                      composite: StageCompositeConfig, device: str = "cpu",
                      progress: bool = False, substitution: bool = False,
                      reserve_bytes: int = 0) -> tuple[Path, float]:
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
    substitution : bool
        Bake every instance's own object too (a replacement shows another one), for the
        stage's substitution; grids kept without one are baked again.
    reserve_bytes : int
        Bytes the caller writes on the same disk after the grids (the variants of a data set).

    Raises
    ------
    regnf.core.preflight.PreflightError
        Before any baking: the grid files and ``reserve_bytes`` would not fit in the space free
        in ``folder`` (the figure and the folder named).
    """
    from regnf.compositor.from_stage import composite_from_scene
    from regnf.compositor.replace import replacement_candidates, swapped
    from regnf.scene_graph import original_selections, read_stage

    index = folder / INDEX
    if _index_checks_out(index, key, substitution):
        return index, 0.0
    scene = read_stage(base)
    originals = original_selections(base, scene)
    config = dataclasses.replace(composite, mode="substitute")
    loaded: dict = {}
    comp = composite_from_scene(scene, originals, base, config, device, loaded=loaded)
    where = replacement_candidates(scene)
    if substitution:
        where = {iid: sorted({*names, scene.instances[iid].library_name}) for iid, names in where.items()}
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
    def fits(nodes: int) -> None:
        what = f"baking {nodes:,} grid nodes" + (" and writing the variants" if reserve_bytes else "")
        check_free_space(folder, nodes * BYTES_PER_NODE + reserve_bytes, what)

    grids = bake_grids(masked_scene(comp.field), objects, cameras, bake, progress, check_nodes=fits)
    folder.mkdir(parents=True, exist_ok=True)
    # An old index stays until the new one replaces it: if this run is killed in between, the
    # files it rewrote no longer match its digests (and the next run bakes again), unless they
    # are the very bytes it records.
    order = sorted(grids.objects)
    jobs = [(grids.scene, folder / SCENE_FILE),
            *((grids.objects[name], folder / f"object_{k}.safetensors") for k, name in enumerate(order))]
    # Writing (with its fsync) and hashing release the interpreter's lock: side by side.
    with cf.ThreadPoolExecutor(usable_cores()) as pool:
        entries = list(pool.map(lambda job: _saved(*job), jobs))
    record = {"config_key": key, "scene": entries[0], "objects": dict(zip(order, entries[1:], strict=True)),
              "nodes": grids.nodes}
    write_json(index, {**record, "substitution": True} if substitution else record)
    return index, grids.seconds


def _saved(grid: BakedField, path: Path) -> dict[str, str]:
    save_baked(grid, path)
    return {"file": path.name, "sha256": sha256_file(path)}


def _entries(record: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [record["scene"], *record["objects"].values()]


def _index_checks_out(index: Path, key: str, substitution: bool = False) -> bool:
    """Whether ``index`` records grids of ``key`` (with every instance's own object, for
    ``substitution``) whose files all have their digests."""
    try:
        record = read_json_input(index, None, "record of baked grids")
        if record.get("config_key") != key or (substitution and record.get("substitution") is not True):
            return False
        entries = _entries(record)
        paths = []
        for entry in entries:
            name = entry["file"]
            if name != Path(name).name or name.startswith(".") or not name.endswith(".safetensors"):
                return False
            paths.append(index.parent / name)
            if not paths[-1].is_file():
                return False
        # Hashing releases the interpreter's lock: the files are hashed side by side.
        with cf.ThreadPoolExecutor(usable_cores()) as pool:
            digests = list(pool.map(sha256_file, paths))
        return all(d == entry["sha256"] for d, entry in zip(digests, entries, strict=True))
    except (OSError, JsonInputError, KeyError, TypeError, AttributeError):
        return False


def load_data_set_grids(index: str | os.PathLike, device: str = "cpu") -> BakedGrids:
    """The grids that ``index`` records (as :func:`bake_for_data_set` wrote them).

    Raises
    ------
    ValueError
        The index is unreadable or malformed, or a grid file is (naming the file).
    """
    index = Path(index)
    try:
        record = read_json_input(index, None, "record of baked grids")
        scene_file = record["scene"]["file"]
        object_files = {str(n): e["file"] for n, e in record["objects"].items()}
        nodes = int(record["nodes"])
    except (OSError, KeyError, TypeError, ValueError) as exc:  # JsonInputError is a ValueError
        raise RegnfError(f"{index}: not a record of baked grids ({type(exc).__name__}: {exc})") from None
    for name in (scene_file, *object_files.values()):
        if not isinstance(name, str) or name != Path(name).name or name.startswith("."):
            raise RegnfError(f"{index}: grid file {name!r} is not a plain file name in {index.parent}")
    return BakedGrids(load_baked(index.parent / scene_file, device),
                      {n: load_baked(index.parent / f, device) for n, f in object_files.items()},
                      float("nan"), nodes)


GRIDS_VERSION = 1
"""Bump when the grids that the same fields, cameras and settings bake change."""


def stage_grids_key(stage: Path, cameras: Sequence[Camera], bake: BakeConfig,
                    composite: StageCompositeConfig) -> str:
    """A key of everything :func:`bake_for_data_set` makes the grids of ``stage`` from.

    The scene field's and every library field's content digest (from their checkpoints'
    headers; loading a field checks it against its bytes), each instance's object, registered
    object and similarity, the cameras, and the bake and removal settings.
    """
    from regnf.io.checkpoint import DIGEST_KEY, read_header
    from regnf.scene_graph import original_selections, read_stage

    scene = read_stage(stage)
    originals = original_selections(stage, scene)
    record = {
        "version": GRIDS_VERSION,
        "scene": read_header(scene.scene.checkpoint).get(DIGEST_KEY),
        "library": {n: [r.label, read_header(r.checkpoint).get(DIGEST_KEY)] for n, r in sorted(scene.library.items())},
        "instances": {i: [r.library_name, originals.get(i), np.round(r.object_to_scene, 9).tolist()]
                      for i, r in sorted(scene.instances.items())},
        "cameras": [[np.round(np.asarray(c.K, np.float64), 6).tolist(),
                     np.round(np.asarray(c.camera_to_world, np.float64), 9).tolist(), c.width, c.height]
                    for c in cameras],
        "bake": dataclasses.asdict(bake),
        "composite": dataclasses.asdict(dataclasses.replace(composite, mode="substitute")),
        "substitution": True,
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]


def cached_stage_grids(root: Path, label: str, stage: Path, cameras: Sequence[Camera], bake: BakeConfig,
                       composite: StageCompositeConfig, device: str = "cpu", progress: bool = False,
                       on_wait: Callable[[str], None] | None = None) -> tuple[BakedGrids, float]:
    """The grids of ``stage`` for its substitution and replacements (:func:`bake_for_data_set`
    with ``substitution``) from ``root/<label>/``, baked there first when they are missing,
    damaged or of another key: (the grids, the seconds spent baking, 0 when read).

    The key is :func:`stage_grids_key`, recorded in the folder's index. One folder per label
    keeps the cache's size bounded: grids of another key (the fields or the registrations
    changed) are baked again over the ones there. The folder's lock is held while the grids are
    checked, baked and read, so two processes wanting the same grids bake them once: the second
    waits for the first (``on_wait`` is told why, with the message naming the lock's holder).
    """
    key = stage_grids_key(stage, cameras, bake, composite)
    folder = root / label
    folder.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(folder_lock(folder, "the baked grids"))
        except LockBusy as busy:
            if on_wait is not None:
                on_wait(f"{folder}: another regnf process ({busy.holder or 'unknown'}) is baking or reading "
                        "these grids; waiting for it")
            stack.enter_context(folder_lock(folder, "the baked grids", timeout=float("inf")))
        index, seconds = bake_for_data_set(stage, folder, key, cameras, bake, composite, device, progress,
                                           substitution=True)
        return load_data_set_grids(index, device), seconds

