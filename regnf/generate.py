"""Scripted synthetic scene generation: many random instance replacements of one stage.

Each variant is one seed. Its instances are swapped for random library objects of their
class (:func:`compositor.replace.pick_replacements`), the composite is rendered from ``K``
orbit cameras (RGB, depth, instance masks, a contact sheet, ``render.json``) and described
by a nerfstudio ``transforms.json``; its replacement layer goes beside the base stage, and
a row of ``manifest.jsonl`` records it (:mod:`regnf.manifest`). Layout of ``out``::

    generation.json                  settings, source stage, config_key
    manifest.jsonl                   one row per variant, sorted by seed
    stage/<name>.usda + assets       the base stage, exported once
    stage/variant_000007.usda        seed 7's replacement layer (over <name>.usda)
    variants/000007/                 seed 7's views, contact_sheet.png, render.json, transforms.json
    errors/000007.txt                the traceback of a variant that failed

Variants run as independent tasks on an executor (:mod:`regnf.executors`): a local process
pool or a Ray cluster, each task with the same pinned thread count, so both give the same
files. A worker renders into a private temporary folder and returns the files' bytes; only
this process writes into ``out``: the files go to a hidden staging folder that is renamed into
place, the layer is written atomically, and the manifest is rewritten after each variant.

A rerun with the same settings skips every variant whose row checks out (files present with
their digests) and makes the others again: those never started, those a kill interrupted
(staging folders are removed), those whose row or files were damaged, and by default those
that failed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from compositor.camera import Camera
from compositor.cameras_io import OrbitConfig, orbit_around_bounds
from compositor.render_folder import RENDER_JSON, RenderConfig
from compositor.stage_config import StageCompositeConfig
from synthetic.atomic_io import write_json, write_text

from .executors import ExecutorConfig, run_tasks
from .manifest import MANIFEST_NAME, read_manifest, sealed, sha256_file, write_manifest

GENERATION_JSON = "generation.json"
"""Settings of the data set in the output folder."""
STAGE_DIR = "stage"
"""Folder of the base stage and the replacement layers."""
VARIANTS_DIR = "variants"
"""Folder of the per-variant folders."""
ERRORS_DIR = "errors"
"""Tracebacks of failed variants."""
UNHASHED = frozenset({RENDER_JSON})
"""Files of a variant left out of its row's digests: render.json holds timings."""


@dataclass(frozen=True)
class GenerateConfig:
    """What :func:`generate` makes and how it runs."""

    variants: int = 10
    """Number of variants (seeds first_seed, first_seed + 1, ...)."""
    first_seed: int = 0
    """Seed of the first variant."""
    cameras: OrbitConfig = field(default_factory=lambda: OrbitConfig(n=8, width=256, height=192))
    """Orbit of cameras inside the scene's bounds; n is the number of views per variant."""
    jitter_cameras: bool = True
    """Turn each variant's orbit by a random azimuth (from its seed) so the variants see the room from
    different places."""
    composite: StageCompositeConfig = field(default_factory=StageCompositeConfig)
    """Removal settings of the substituted instances (the mode is always substitute)."""
    render: RenderConfig = field(default_factory=lambda: RenderConfig(progress=False))
    """Renderer settings (the progress bar per variant is off: the run shows one over variants)."""
    executor: ExecutorConfig = field(default_factory=ExecutorConfig)
    """Where the variants run."""
    retry_failed: bool = True
    """Make variants that failed in an earlier run again (finished ones are always kept)."""
    device: str = "cpu"
    """Torch device of the workers."""

    def __post_init__(self) -> None:
        if self.variants < 1:
            raise ValueError(f"variants must be >= 1, got {self.variants}")
        if self.first_seed < 0:
            raise ValueError(f"first_seed must be >= 0, got {self.first_seed}")

    @property
    def seeds(self) -> list[int]:
        """The seeds of the variants."""
        return list(range(self.first_seed, self.first_seed + self.variants))

    def output_settings(self) -> dict[str, Any]:
        """Every setting that changes what a variant's files hold (not how or where it runs)."""
        render = dataclasses.replace(self.render, progress=False, overwrite=False)
        return {
            "cameras": dataclasses.asdict(self.cameras),
            "jitter_cameras": self.jitter_cameras,
            "composite": dataclasses.asdict(dataclasses.replace(self.composite, mode="substitute")),
            "render": dataclasses.asdict(render),
            "threads_per_task": self.executor.threads_per_task,
            "device": self.device,
        }


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


class VariantOutput(NamedTuple):
    """What a worker returns: the variant's files as bytes, and what it chose."""

    seed: int
    """The variant's seed."""
    selections: dict[str, str]
    """Instance id -> library object shown."""
    instance_ids: dict[str, int]
    """Instance id -> id in the instance images."""
    files: dict[str, bytes]
    """File name -> content (views, contact sheet, render.json, transforms.json)."""
    seconds: float
    """Time the worker spent (loading, composing, rendering)."""


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


def variant_name(seed: int) -> str:
    """Folder name of a variant: the seed on 6 digits."""
    return f"{seed:06d}"


def layer_name(seed: int) -> str:
    """File name of a variant's replacement layer."""
    return f"variant_{variant_name(seed)}.usda"


def variant_cameras(bounds: np.ndarray, config: GenerateConfig, seed: int) -> list[Camera]:
    """The cameras of variant ``seed``: the configured orbit, turned by a seeded azimuth if jittered."""
    orbit = config.cameras
    if config.jitter_cameras:
        # A generator of its own (not the replacement choices'), so the choices stay those of
        # `regnf replace --seed`.
        rng = np.random.default_rng([seed, 1])
        offset = orbit.azimuth_offset_deg + float(rng.uniform(0.0, 360.0 / orbit.n))
        orbit = dataclasses.replace(orbit, azimuth_offset_deg=offset)
    return orbit_around_bounds(bounds, orbit)


# Per worker process: the stage as read and its loaded fields, kept across the variants it runs.
_WORKER_CACHE: dict[str, Any] = {}


def render_variant(task: VariantTask) -> VariantOutput:
    """Make one variant in a private temporary folder and return its files (runs in a worker)."""
    from compositor.from_stage import composite_from_scene, original_selections
    from compositor.nerfstudio import transforms_json
    from compositor.render_folder import render_views
    from compositor.replace import pick_replacements, swapped
    from scene_graph import read_stage

    t0 = time.perf_counter()
    base = Path(task.base_stage)
    stamp = (str(base), base.stat().st_mtime_ns)
    if _WORKER_CACHE.get("stamp") != stamp:
        _WORKER_CACHE.clear()
        scene = read_stage(base)
        _WORKER_CACHE.update(stamp=stamp, scene=scene, originals=original_selections(base, scene), fields={})
    scene = _WORKER_CACHE["scene"]
    selections = pick_replacements(scene, task.seed)
    comp = composite_from_scene(swapped(scene, selections), _WORKER_CACHE["originals"], base,
                                dataclasses.replace(task.composite, mode="substitute"), task.device,
                                loaded=_WORKER_CACHE["fields"])
    shown = {iid: inst.library_name for iid, inst in comp.scene.instances.items()}
    if shown != selections:
        raise RuntimeError(f"the composite shows {shown}, expected {selections}")
    rel_layer = f"../../{STAGE_DIR}/{task.layer_name}"
    metadata = {"stage": rel_layer, "mode": "substitute", "seed": task.seed, "selections": selections,
                "instance_ids": comp.instance_ids}
    with tempfile.TemporaryDirectory(prefix="regnf-variant-") as tmp:
        report = render_views(comp.field, task.cameras, tmp, task.render, metadata)
        extra = {"seed": task.seed, "stage": rel_layer, "selections": selections,
                 "instance_ids": comp.instance_ids,
                 "mask": "instance PNG, uint16 id + 1 (0 background)", "depth_unit_scale_factor": 1e-3}
        tj = transforms_json(task.cameras, report.views, extra)
        (Path(tmp) / "transforms.json").write_text(json.dumps(tj, indent=2) + "\n")
        files = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir()) if p.is_file()}
    return VariantOutput(task.seed, selections, comp.instance_ids, files, time.perf_counter() - t0)


def _settings_key(settings: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def _source_summary(stage: Path) -> dict[str, Any]:
    """What of the source stage the variants depend on: its instances, library and scene field."""
    from scene_graph import read_stage

    scene = read_stage(stage)
    return {
        "scene": scene.scene.name,
        "library": {n: r.label for n, r in sorted(scene.library.items())},
        "instances": {i: {"library_name": r.library_name,
                          "object_to_scene": np.round(r.object_to_scene, 9).tolist()}
                      for i, r in sorted(scene.instances.items())},
    }


def prepare_output(stage: str | os.PathLike, out: Path, config: GenerateConfig) -> tuple[Path, str]:
    """Check or write ``generation.json``, export the base stage once; return (base, config_key).

    Raises
    ------
    ValueError
        ``out`` holds a data set of another stage or other settings (naming the file).
    """
    from scene_graph import export_stage

    src = Path(stage).absolute()
    settings = config.output_settings()
    source = _source_summary(src)
    key = _settings_key({"settings": settings, "source": source})
    meta_path = out / GENERATION_JSON
    base = out / STAGE_DIR / (src.stem + ".usda")
    if meta_path.exists():
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{meta_path}: unreadable ({exc}); remove it or choose another output folder") from exc
        if meta.get("config_key") != key:
            raise ValueError(f"{meta_path}: {out} holds variants of another stage or other settings "
                             f"(config_key {meta.get('config_key')}, now {key}); choose another output folder")
        base = out / meta.get("base_stage", str(base.relative_to(out)))
    out.mkdir(parents=True, exist_ok=True)
    if not base.is_file():
        # export_stage writes the root layer last: its presence means a complete base stage.
        # Without it, whatever is in the stage folder is from an interrupted export.
        shutil.rmtree(base.parent, ignore_errors=True)
        export_stage(src, base)
    write_json(meta_path, {"config_key": key, "source_stage": str(src), "base_stage": str(base.relative_to(out)),
                           "settings": settings, "source": source})
    return base, key


def _clean_partials(out: Path) -> None:
    """Remove what an interrupted run left behind: staging folders and temporary files.

    Every write here goes through a hidden temporary (``.<name>.*``) that is renamed into
    place; one that is still there was never finished.
    """
    stage_dir = out / STAGE_DIR
    leftovers = [*out.glob(".*"), *(out / VARIANTS_DIR).glob(".*"), *(out / ERRORS_DIR).glob(".*"),
                 *stage_dir.rglob(".*")]
    for p in leftovers:
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def commit_variant(out: Path, base: Path, output: VariantOutput, key: str) -> dict[str, Any]:
    """Write a worker's files into place (staging folder, then rename) and its layer; return its row."""
    from scene_graph import make_replacement_layer

    name = variant_name(output.seed)
    folder = out / VARIANTS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=folder))
    try:
        for fname, data in output.files.items():
            (staging / fname).write_bytes(data)
        layer = make_replacement_layer(base, output.selections, base.parent / layer_name(output.seed))
        final = folder / name
        if final.exists():
            shutil.rmtree(final)
        os.replace(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    files = {f: sha256_file(final / f) for f in sorted(output.files) if f not in UNHASHED}
    views = sum(1 for f in output.files if f.startswith("rgb_"))
    return sealed({
        "seed": output.seed, "status": "ok", "config_key": key,
        "variant": f"{VARIANTS_DIR}/{name}", "layer": str(layer.relative_to(out)),
        "layer_sha256": sha256_file(layer), "selections": output.selections,
        "instance_ids": output.instance_ids, "views": views, "files": files,
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
        ``out`` holds a data set of other settings, or the stage cannot be read (a
        ``scene_graph.StageError`` naming the file).
    """
    from tqdm import tqdm

    from compositor.cameras_io import field_bounds_metres
    from compositor.from_stage import composite_from_stage

    t0 = time.perf_counter()
    out = Path(out).absolute()
    base, key = prepare_output(stage, out, config)
    state = read_manifest(out, key)
    rows = dict(state.rows)
    done = [s for s in config.seeds if s in rows and (rows[s]["status"] == "ok" or not config.retry_failed)]
    todo = [s for s in config.seeds if s not in done]
    _clean_partials(out)
    for s in todo:
        rows.pop(s, None)
    write_manifest(out, rows.values())  # drops the rejected rows at once
    if not todo:
        return GenerationReport(out, out / MANIFEST_NAME, [], done, {}, state.problems, time.perf_counter() - t0)
    scene_only = composite_from_stage(base, dataclasses.replace(config.composite, mode="scene"), "cpu")
    bounds = field_bounds_metres(scene_only.field.scene)
    del scene_only
    render = dataclasses.replace(config.render, progress=False, overwrite=False)
    tasks = [VariantTask(str(base), s, variant_cameras(bounds, config, s), layer_name(s), config.composite,
                         render, config.device) for s in todo]
    failed: dict[int, str] = {}
    made: list[int] = []
    bar = tqdm(total=len(tasks), desc=f"generate ({config.executor.kind})", unit="variant", disable=not progress)
    for outcome in run_tasks(render_variant, tasks, config.executor):
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
            (out / ERRORS_DIR / f"{variant_name(seed)}.txt").unlink(missing_ok=True)
        rows[seed] = row
        write_manifest(out, rows.values())
        if on_variant is not None:
            on_variant(row)
        bar.update(1)
        bar.set_postfix(failed=len(failed))
    bar.close()
    return GenerationReport(out, out / MANIFEST_NAME, sorted(made), done, failed, state.problems,
                            time.perf_counter() - t0)


def variants_per_minute(report: GenerationReport) -> float:
    """Variants made per minute of wall time in a run (NaN if none)."""
    n = len(report.made) + len(report.failed)
    return n / (report.seconds / 60.0) if n and report.seconds > 0 else math.nan


def load_rows(out: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of ``out/manifest.jsonl`` as written (unchecked), in seed order."""
    path = Path(out) / MANIFEST_NAME
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def tile_sheet(out: str | os.PathLike, seeds: Sequence[int] | None = None, columns: int = 0) -> Path:
    """``out/contact_sheet.png``: the first view of each finished variant, tiled in seed order."""
    from compositor.contact_sheets import contact_sheet
    from compositor.image_io import read_rgb_png, write_rgb_png

    out = Path(out)
    rows = [r for r in load_rows(out) if r["status"] == "ok" and (seeds is None or r["seed"] in seeds)]
    if not rows:
        raise ValueError(f"{out / MANIFEST_NAME}: no finished variant to show")
    thumbs = [read_rgb_png(out / r["variant"] / "rgb_0000.png") for r in rows]
    path = out / "contact_sheet.png"
    write_rgb_png(path, contact_sheet(thumbs, columns, 160))
    return path
