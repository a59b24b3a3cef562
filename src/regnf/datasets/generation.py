"""Scripted synthetic scene generation: many random instance replacements of one stage.

Each variant is one seed. Its instances are swapped for random library objects of their
class (:func:`regnf.compositor.replace.pick_replacements`), each optionally turned and moved
on its support plane where that collides with nothing (``jitter_yaw_deg``, ``jitter_shift``:
:mod:`regnf.datasets.placement_jitter`; the captured objects stay removed where they were), the
composite is rendered from ``K`` orbit cameras (RGB, depth, instance masks, a contact sheet,
``render.json``), labelled with a class image per view, its camera's exposure and white
balance varied from the seed (:mod:`regnf.datasets.variation`), and described by the formats asked for
(``format``: a nerfstudio ``transforms.json``, COCO annotations; :mod:`regnf.datasets.variant_labels`);
its replacement layer (the selections, and the moved instances' poses) goes beside the base
stage, and a row of ``manifest.jsonl`` records it with each instance's 3D box and, with a
placement jitter, each instance's placement (:mod:`regnf.datasets.manifest`). A worker process makes
each variant (:mod:`regnf.datasets.generate_worker`); this module drives the run and puts each variant
in place. Instance images hold
instance ids 1..n, 0 for the background and the room, in every format; 3D boxes and BOP poses
are those of the poses shown.

The cameras (``camera_source``) are an orbit inside the scene's bounds, turned by a seeded
azimuth per variant, or ``cameras.n`` frames of a capture the user names (``capture``, any
capture format; :func:`capture_views`): each variant's own seeded choice of frames
(:func:`variant_frames`), or the same evenly spaced ones, posed and with the intrinsics the
capture has, ``cameras.width`` wide at the capture's aspect ratio. Their frame indices are in
the variant's manifest row, ``transforms.json`` and ``render.json`` (``capture_frames``); the
capture's path and identity (frame count, size, a digest of its cameras) in ``generation.json``,
the identity in the config_key. Layout of ``out``::

    .regnf-output.json               marker: a folder made by regnf generate (regnf.core.output_dir)
    .regnf.lock                      the lock a run holds (regnf.core.file_lock)
    generation.json                  settings, source stage, config_key
    manifest.jsonl                   one row per variant, sorted by seed
    stage/<name>.usda + assets       the base stage, exported once
    stage/variant_000007.usda        seed 7's replacement layer (over <name>.usda)
    variants/000007/                 seed 7's views (rgb_k, depth_k, instance_k, class_k .png),
                                     contact_sheet.png, render.json, transforms.json (nerfstudio),
                                     coco.json (COCO: the variant's part)
    coco/annotations.json            COCO: every finished variant's images and annotations
    bop/                             BOP: models/, camera.json, train/000007/ (seed 7's scene)
    errors/000007.txt                the traceback of a variant that failed
    baked/                           with the baked renderer: the grids every variant reads
                                     (index.json, scene.safetensors, object_*.safetensors)

The output folder is the run's own (:func:`regnf.core.output_dir.claim_output_dir`): a new
or empty folder, or one an earlier ``generate`` made. A folder that holds anything else
(the user's files, a source stage, another command's output) is refused before anything is
written, unless ``reuse`` says to write into it anyway; even then nothing there is removed
or written over but the names above. The source stage may not lie in ``out/stage/``
(exports and layers are written there).

A run holds the folder's lock from start to end: a second run into the same folder (from
this machine or another one sharing the folder) fails at once with
:class:`regnf.core.file_lock.LockBusy`. The lock is a POSIX record lock: it works on local
disks and on NFS with locking (NFSv4, or NFSv3 with ``lockd``); where the file system has no
locks, the run fails with :class:`regnf.core.file_lock.LockUnavailable` instead of going on
unprotected.

With ``render.renderer`` ``baked``, the fields are baked once per data set, before the first
variant (:func:`bake_for_data_set`): the scene less its removal regions (the same in every
variant) and every library object a variant may show, each at the finest cell its places in
the scene need for the views' pixel footprint (the orbit's; or every capture frame a variant
may take), each on one CPU thread (the same grids on any machine). The grids go to ``baked/``
and every worker reads them there; a rerun keeps them when their record and digests check out. Every sphere-tracing step of a variant then reads grids
(trilinear look-ups), not networks; ``regnf bench render`` measures what that costs in PSNR.

Variants run as independent tasks on an executor (:mod:`regnf.core.executors`): a local process
pool or a Ray cluster, each task with the same pinned thread count, so both give the same
files. A worker renders into a private folder under the run's scratch folder
(``out/.regnf-tmp-work-*``) and returns the files' bytes; only this process writes the data
set: the files go to a staging folder (``variants/.regnf-tmp-<seed>-*``) that is renamed
into place, the layer is written atomically, and the variant's row is appended to the
manifest. Tasks are built :data:`TASKS_PER_BATCH` at a time, not for every seed at once.

A rerun with the same settings skips every variant whose row checks out (files present with
their digests) and makes the others again: those never started, those a kill interrupted,
those whose row or files were damaged, and by default those that failed. What a killed run
left behind (entries named ``.regnf-tmp-*`` in ``out``, ``variants/``, ``errors/`` and
``stage/``) is removed first, under the lock; nothing else is.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from regnf.compositor.cameras_io import orbit_around_bounds
from regnf.compositor.render_folder import RENDER_JSON, RenderConfig
from regnf.core.atomic_io import write_json, write_text
from regnf.core.errors import RegnfError
from regnf.core.executors import call_pinned, local_pool, run_tasks
from regnf.core.file_lock import folder_lock
from regnf.core.output_dir import (
    claim_output_dir,
    owned_output_dir,
    remove_leftovers,
    replace_entry,
    staging_dir,
)
from regnf.core.preflight import JsonInputError, read_json_input

from .bop import BOP_DIR, ModelPlan
from .coco import COCO_DIR
from .data_set_formats import (
    bop_scene_folder,
    commit_bop_scene,
    write_bop_models,
    write_coco,
)
from .generate_cameras import (
    CaptureViews,
    at_capture_size,
    capture_views,
    variant_cameras,
    variant_frames,
)
from .generate_config import GenerateConfig
from .generate_disk import check_generation_disk, variant_bytes
from .generate_layout import STAGE_DIR, VARIANTS_DIR, layer_name, variant_name
from .generate_source import check_source, check_variant_sizes, source_summary
from .generate_worker import VariantOutput, VariantTask, render_variant, warm_worker
from .manifest import (
    MANIFEST_NAME,
    append_row,
    load_rows,
    read_manifest,
    sealed,
    sha256_file,
    write_manifest,
)
from .placement_jitter import record_in_layer

GENERATION_JSON = "generation.json"
"""Settings of the data set in the output folder."""
ERRORS_DIR = "errors"
"""Tracebacks of failed variants."""
BAKED_DIR = "baked"
"""Grids of the baked renderer (:func:`bake_for_data_set`)."""
UNHASHED = frozenset({RENDER_JSON})
"""Files of a variant left out of its row's digests: render.json holds timings."""
CONTACT_SHEET = "contact_sheet.png"
"""The first view of the first finished variants, tiled (:func:`tile_sheet`)."""
LAYOUT = (GENERATION_JSON, MANIFEST_NAME, STAGE_DIR, VARIANTS_DIR, ERRORS_DIR, CONTACT_SHEET, BAKED_DIR,
          COCO_DIR, BOP_DIR)
"""The top-level entries a run writes in its output folder (besides the marker and the lock)."""
KIND = "generate"
"""Kind of command recorded in the output folder's marker."""
WORK_LABEL = "work"
"""Label of the run's scratch folder, ``out/.regnf-tmp-work-*``, where workers render."""
STAGE_LOCK_WAIT_S = 60.0
"""Seconds a run waits for the lock of ``out/stage/`` (held by stage writers, see
:mod:`scene_graph`) before it cleans leftovers there."""
MAX_SHEET_TILES = 256
"""Variants shown on the data set's contact sheet (the first ones in seed order): one tile each,
so a sheet of every variant of a large data set would be an image of gigabytes."""
TASKS_PER_BATCH = 1024
"""Variants handed to the executor at a time. Their tasks (each with its cameras) are built
per batch rather than for every seed up front, and the executor holds only these; a batch is
large enough that the pause between batches (the pool drains and starts again) costs about
a variant per worker per batch."""


class GenerationReport(NamedTuple):
    """What :func:`generate` did."""

    out: Path
    """The output folder."""
    manifest: Path
    """``out/manifest.jsonl``."""
    made: list[int]
    """Seeds made in this run."""
    skipped: list[int]
    """Seeds already done and checked."""
    failed: dict[int, str]
    """Seed -> error, for the variants that failed in this run."""
    problems: list[str]
    """Rows of the earlier manifest that were rejected (and made again)."""
    seconds: float
    """Wall time of this run."""
    bake_seconds: float = 0.0
    """Of which baking the grids of the baked renderer (0 when kept from an earlier run)."""
    notes: tuple[str, ...] = ()
    """What the user should know about the output (each said once)."""


def _settings_key(settings: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def prepare_output(stage: str | os.PathLike, out: str | os.PathLike, config: GenerateConfig,
                   source: dict[str, Any] | None = None,
                   capture: CaptureViews | None = None) -> tuple[Path, str]:
    """Claim ``out``, check or write ``generation.json``, export the base stage; return (base, config_key).

    The export is done once: a rerun whose ``generation.json`` records the same settings and
    source keeps the base stage it finds. Without that record, or without the base stage's
    root layer, the stage is exported again over what is there: the export writes every file
    of the stage (each through a temporary file) and nothing else, so a half-done export is
    completed and no other file in ``out/stage/`` is touched. :func:`generate` calls this
    while holding the folder's lock.

    Parameters
    ----------
    stage : str or PathLike
        The source stage.
    out : str or PathLike
        The output folder.
    config : GenerateConfig
    source : dict, optional
        What of the source stage the variants depend on (:func:`source_summary`), if the
        caller has read it already.
    capture : CaptureViews, optional
        With capture cameras, the capture (:func:`capture_views`), if the caller has read it
        already. Its identity is part of the config_key, and generation.json records it and
        its path (the path is not keyed: the same capture elsewhere gives the same data set).

    Raises
    ------
    ValueError
        The source stage is inside ``out/stage/``; ``out`` is refused
        (:class:`regnf.core.output_dir.OutputFolderError`); ``out`` holds a data set of another
        stage, capture or other settings (naming the file); the stage or the capture cannot be read.
    """
    from regnf.scene_graph import export_stage

    src = Path(stage).absolute()
    out = Path(out).absolute()
    check_source(src, out)
    source = source_summary(src) if source is None else source  # a stage that cannot be read: nothing written
    if capture is None:
        capture = capture_views(config)  # nor a capture that cannot be
    config = at_capture_size(config, capture)
    claim_output_dir(out, KIND, config.reuse)
    settings = config.output_settings()
    # Orbit data sets: the key of those made before capture cameras.
    shots = {} if capture is None else {"capture": capture.identity}
    key = _settings_key({"settings": settings, "source": source, **shots})
    meta_path = out / GENERATION_JSON
    base = out / STAGE_DIR / (src.stem + ".usda")
    recorded = False
    if meta_path.exists():
        try:
            meta = read_json_input(meta_path, None, "data set record")
        except JsonInputError as exc:
            raise RegnfError(f"{meta_path}: unreadable ({exc.problem}); remove it or choose another output "
                             "folder") from exc
        if meta.get("config_key") != key:
            before = meta.get("capture") if isinstance(meta.get("capture"), dict) else {}
            if capture is not None and before.get("cameras_sha256") != capture.identity["cameras_sha256"]:
                raise RegnfError(f"{meta_path}: {out} holds variants of another capture than {capture.path} "
                                 f"(or of orbit cameras); choose another output folder")
            raise RegnfError(f"{meta_path}: {out} holds variants of another stage or other settings "
                             f"(config_key {meta.get('config_key')}, now {key}); choose another output folder")
        rel = Path(str(meta.get("base_stage", base.relative_to(out))))
        if rel.is_absolute() or ".." in rel.parts or rel.parts[:1] != (STAGE_DIR,):
            raise RegnfError(f"{meta_path}: base_stage {str(rel)!r} is not inside {STAGE_DIR}/; "
                             "remove the file or choose another output folder")
        base, recorded = out / rel, True
    if not (recorded and base.is_file()):
        # export_stage writes the root layer last: with it and the record, the base stage is
        # complete; otherwise what is there is (part of) an export that the new one completes.
        export_stage(src, base)
    write_json(meta_path, {"config_key": key, "source_stage": str(src), "base_stage": str(base.relative_to(out)),
                           "settings": settings, "source": source,
                           **({} if capture is None else {"capture": {"path": str(capture.path), **capture.identity}})})
    return base, key


def _remove_leftovers(out: Path) -> None:
    """Remove what killed runs left in the data set's folders: entries named ``.regnf-tmp-*``.

    The caller holds the output folder's lock (its top level is cleaned when it is taken);
    ``stage/`` is cleaned under the stage folder's lock too, the one stage writers take.
    """
    for sub in (VARIANTS_DIR, ERRORS_DIR, BAKED_DIR):
        remove_leftovers(out / sub)
    stage_dir = out / STAGE_DIR
    if stage_dir.is_dir():
        # Stage writers hold this lock for about a second per edit: wait for one, as they do.
        with folder_lock(stage_dir, "the data set's base stage", STAGE_LOCK_WAIT_S):
            remove_leftovers(stage_dir, recursive=True)


def _plain_name(name: str) -> str:
    """``name`` if it is a plain, visible file name (a worker's file list is checked before use)."""
    if not name or name != Path(name).name or name.startswith("."):
        raise RegnfError(f"a worker returned a file named {name!r}, not a plain file name")
    return name


def commit_variant(out: Path, base: Path, output: VariantOutput, key: str) -> dict[str, Any]:
    """Write a worker's files into place (staging folder, then rename) and its layer; return its row.

    An earlier ``variants/<seed>`` is replaced: it is this data set's (the seed is made again).
    """
    from regnf.scene_graph import make_replacement_layer

    name = variant_name(output.seed)
    folder = out / VARIANTS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    final = folder / name
    with staging_dir(folder, name) as staging:  # removed on any error
        for fname, data in output.files.items():
            (staging / _plain_name(fname)).write_bytes(data)
        layer = make_replacement_layer(base, output.selections, base.parent / layer_name(output.seed))
        if output.placement:  # the moved instances' poses, so that the layer composes to the views
            record_in_layer(layer, {i: np.asarray(p["object_to_scene"]) for i, p in output.placement.items()
                                    if p["moved"]})
        replace_entry(staging, final)
    if output.bop_files is not None:
        commit_bop_scene(out, output.seed, output.bop_files, json.loads(output.files[RENDER_JSON])["cameras"][0])
    files = {f: sha256_file(final / f) for f in sorted(output.files) if f not in UNHASHED}
    views = sum(1 for f in output.files if f.startswith("rgb_"))
    return sealed({
        "seed": output.seed, "status": "ok", "config_key": key,
        "variant": f"{VARIANTS_DIR}/{name}", "layer": str(layer.relative_to(out)),
        "layer_sha256": sha256_file(layer), "selections": output.selections,
        "instance_ids": output.instance_ids, "boxes": output.boxes, "appearance": output.appearance,
        "views": views, "files": files,
        **({} if output.frames is None else {"capture_frames": list(output.frames)}),
        **({} if output.placement is None else {"placement": output.placement}),
    })


def failed_row(out: Path, seed: int, error: str, key: str) -> dict[str, Any]:
    """The row of a failed variant; its traceback goes to ``errors/<seed>.txt``."""
    write_text(out / ERRORS_DIR / f"{variant_name(seed)}.txt", error)
    return sealed({"seed": seed, "status": "failed", "config_key": key, "error": error.splitlines()[0]})


def generate(
    stage: str | os.PathLike,
    out: str | os.PathLike,
    config: GenerateConfig = GenerateConfig(),
    progress: bool = True,
    on_variant: Callable[[dict[str, Any]], None] | None = None,
) -> GenerationReport:
    """Generate ``config.variants`` random replacements of ``stage`` into ``out`` (see the module).

    Parameters
    ----------
    stage : str or PathLike
        A regnf stage (.usda / .usdc / .usdz) with registered instances.
    out : str or PathLike
        Output folder; rerunning into it resumes.
    config : GenerateConfig
    progress : bool
        Show a progress bar over the variants.
    on_variant : callable, optional
        Called with each new manifest row, as variants finish.

    Returns
    -------
    GenerationReport

    Raises
    ------
    ValueError
        The source stage is inside ``out/stage/``; a variant could swap in an object of
        another size (:class:`~regnf.compositor.size_change.SizeChangeError`, unless
        ``config.allow_size_change``); ``out`` holds files regnf generate did
        not make and ``config.reuse`` is off (:class:`regnf.core.output_dir.OutputFolderError`);
        ``out`` holds a data set of other settings; the stage cannot be read (a
        ``scene_graph.StageError`` naming the file); with capture cameras, the capture is
        missing or not a capture (a ``CaptureError`` naming the file) or has fewer frames than
        ``cameras.n``. Nothing is written then.
    regnf.core.file_lock.LockBusy
        Another run is writing into ``out`` (a ``RuntimeError``); nothing is written.
    regnf.core.file_lock.LockUnavailable
        ``out``'s file system cannot take locks (an ``OSError``).
    """
    t0 = time.perf_counter()
    out = Path(out).absolute()
    # The source is checked and read before the folder is claimed: a refusal writes nothing.
    check_source(stage, out)
    capture = capture_views(config)  # capture cameras: the capture read and checked, or one line
    config = at_capture_size(config, capture)
    if not config.allow_size_change:
        check_variant_sizes(Path(stage).absolute())
    source = source_summary(Path(stage).absolute())
    check_generation_disk(stage, out, config)
    with owned_output_dir(out, KIND, config.reuse, "the data set folder"):
        _remove_leftovers(out)
        base, key = prepare_output(stage, out, config, source, capture)
        state = read_manifest(out, key)
        rows = dict(state.rows)
        # A finished variant whose BOP scene is gone (removed, or a run killed between the two)
        # is made again.
        done = [s for s in config.seeds if s in rows and (rows[s]["status"] == "ok" or not config.retry_failed)
                and not ("bop" in config.formats and rows[s]["status"] == "ok"
                         and not bop_scene_folder(out, s).is_dir())]
        kept = set(done)
        todo = [s for s in config.seeds if s not in kept]
        for s in todo:
            rows.pop(s, None)
        write_manifest(out, rows.values())  # drops the rejected rows at once
        made: list[int] = []
        failed: dict[int, str] = {}
        timings: dict[str, float] = {}
        models = (lambda: write_bop_models(out, base, source)) if "bop" in config.formats else None
        notes: list[str] = []
        if todo:
            _make_variants(out, base, key, config, todo, rows, made, failed, progress, on_variant, timings,
                           capture, models, notes)
            write_manifest(out, rows.values())  # sorted by seed again
        elif models is not None:
            notes += models()[1]
        if "coco" in config.formats:
            write_coco(out, rows, config.cameras.n, source)
    return GenerationReport(out, out / MANIFEST_NAME, sorted(made), done, failed, state.problems,
                            time.perf_counter() - t0, timings.get("bake", 0.0), tuple(notes))


def _make_variants(out: Path, base: Path, key: str, config: GenerateConfig, todo: list[int],
                   rows: dict[int, dict[str, Any]], made: list[int], failed: dict[int, str], progress: bool,
                   on_variant: Callable[[dict[str, Any]], None] | None, timings: dict[str, float],
                   capture: CaptureViews | None = None,
                   bop_models: Callable[[], tuple[ModelPlan, list[str]]] | None = None,
                   notes: list[str] | None = None) -> None:
    """Run the variants of ``todo`` and commit each as it finishes (``rows``, ``made``, ``failed``
    and ``timings`` are updated); their cameras are ``capture``'s frames when it is given, and
    their BOP scenes are made with the models ``bop_models`` writes when it is given (its notes
    go to ``notes``)."""
    from regnf.compositor.cameras_io import field_bounds_metres
    from regnf.compositor.from_stage import composite_from_stage

    stack = contextlib.ExitStack()
    warm = None
    if config.executor.kind == "local":
        # The first batch's workers start now, and import the renderer and read the stage
        # while this process prepares (and bakes): a worker's start is much of the first
        # variant's time (docs/decisions/rendering-speed.md).
        width = min(config.executor.width, len(todo), TASKS_PER_BATCH)
        warm = stack.enter_context(local_pool(width, config.executor.threads_per_task))
        for _ in range(width):
            warm.submit(call_pinned, warm_worker, config.executor.threads_per_task, str(base))
    with stack:
        bop_plan = None
        if bop_models is not None:  # while the warm workers start: the models need no baking
            bop_plan, said = bop_models()
            if notes is not None:
                notes += said
        scene_only = composite_from_stage(base, dataclasses.replace(config.composite, mode="scene"), "cpu")
        bounds = field_bounds_metres(scene_only.field.scene)
        del scene_only
        render = dataclasses.replace(config.render, progress=False, overwrite=False)
        baked = None
        if render.renderer == "baked":
            from .data_set_grids import bake_for_data_set

            # The orbit unturned: the turns move the cameras around, not nearer or farther. Capture
            # cameras: every frame a variant may take (the same frames for all, unjittered).
            if capture is None:
                orbit = orbit_around_bounds(bounds, config.cameras)
            elif config.jitter_cameras:
                orbit = capture.cameras
            else:
                orbit = variant_cameras(bounds, config, config.first_seed, capture)
            index, timings["bake"] = bake_for_data_set(base, out / BAKED_DIR, key, orbit, render.bake,
                                                       config.composite, config.device, progress,
                                                       reserve_bytes=len(todo) * variant_bytes(config))
            baked = str(index)
        _run_variants(out, base, key, config, todo, rows, made, failed, progress, on_variant, bounds, render,
                      baked, stack, warm, capture, bop_plan)


def _run_variants(out: Path, base: Path, key: str, config: GenerateConfig, todo: list[int],
                  rows: dict[int, dict[str, Any]], made: list[int], failed: dict[int, str], progress: bool,
                  on_variant: Callable[[dict[str, Any]], None] | None, bounds: np.ndarray, render: RenderConfig,
                  baked: str | None, stack: contextlib.ExitStack, warm: Any,
                  capture: CaptureViews | None = None, bop_plan: ModelPlan | None = None) -> None:
    """The variants of :func:`_make_variants`, :data:`TASKS_PER_BATCH` at a time; the first
    batch in the pool ``warm`` (started early, closed with ``stack``) when there is one."""
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc=f"generate ({config.executor.kind})", unit="variant", disable=not progress)
    # Workers render under out (every node of a cluster sees it); the folder goes at the end,
    # or, if this run is killed, when the next one takes the lock.
    with staging_dir(out, WORK_LABEL) as scratch:
        for first in range(0, len(todo), TASKS_PER_BATCH):
            tasks = [VariantTask(str(base), s, variant_cameras(bounds, config, s, capture), layer_name(s),
                                 config.composite, render, config.device, str(scratch), baked, config.formats,
                                 (config.exposure_stops, config.white_balance),
                                 placement=(config.jitter_yaw_deg, config.jitter_shift), bop=bop_plan,
                                 frames=None if capture is None else tuple(variant_frames(config, s,
                                                                                          len(capture.cameras))))
                     for s in todo[first:first + TASKS_PER_BATCH]]
            # Later batches in pools of their own: a worker that died (killed, out of memory)
            # breaks its pool, and fails that batch's remaining variants only.
            pool = warm if first == 0 else None
            for outcome in run_tasks(render_variant, tasks, config.executor, pool):
                seed = tasks[outcome.index].seed
                if outcome.error is None:
                    try:
                        row = commit_variant(out, base, outcome.value, key)
                    except Exception as exc:  # noqa: BLE001 (e.g. the layer cannot be written: record, go on)
                        row = failed_row(out, seed, f"{type(exc).__name__}: {exc}", key)
                else:
                    row = failed_row(out, seed, outcome.error, key)
                if row["status"] == "failed":
                    failed[seed] = row["error"]
                else:
                    made.append(seed)
                    # An earlier run's traceback of this seed (this data set's own file).
                    (out / ERRORS_DIR / f"{variant_name(seed)}.txt").unlink(missing_ok=True)
                rows[seed] = row
                append_row(out, row)
                if on_variant is not None:
                    on_variant(row)
                bar.update(1)
                bar.set_postfix(failed=len(failed))
            if pool is not None:
                stack.close()  # the warm pool's workers go
    bar.close()


def variants_per_minute(report: GenerationReport) -> float:
    """Variants made per minute of wall time in a run (NaN if none)."""
    n = len(report.made) + len(report.failed)
    return n / (report.seconds / 60.0) if n and report.seconds > 0 else math.nan


def tile_sheet(out: str | os.PathLike, seeds: Sequence[int] | None = None, columns: int = 0,
               limit: int = MAX_SHEET_TILES) -> Path:
    """``out/contact_sheet.png``: the first view of the first ``limit`` finished variants, tiled in seed order.

    Written under the data set folder's lock (it is one of the data set's files).

    Raises
    ------
    ValueError
        No finished variant (among ``seeds``, if given).
    regnf.core.file_lock.LockBusy
        A run is writing into ``out`` now.
    """
    from regnf.compositor.contact_sheets import contact_sheet
    from regnf.core.image_io import read_rgb_png, write_rgb_png

    out = Path(out)
    wanted = None if seeds is None else set(seeds)
    with folder_lock(out, "the data set folder"):
        rows = [r for r in load_rows(out) if r["status"] == "ok" and (wanted is None or r["seed"] in wanted)]
        if not rows:
            raise RegnfError(f"{out / MANIFEST_NAME}: no finished variant to show")
        thumbs = [read_rgb_png(out / r["variant"] / "rgb_0000.png") for r in rows[:limit]]
        path = out / CONTACT_SHEET
        write_rgb_png(path, contact_sheet(thumbs, columns, 160))
    return path
