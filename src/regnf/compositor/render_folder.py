"""Render a field from many cameras into a folder: images, a contact sheet and ``render.json``.

Per view ``k`` (4 digits): ``rgb_k.png`` (8-bit), ``depth_k.png`` (16-bit millimetres, 0 no
hit) and ``instance_k.png`` (16-bit: ``i`` where instance ``i`` is seen, 0 on the background and
the scene's own surfaces); see :mod:`regnf.core.image_io`. Then ``contact_sheet.png`` (the RGB views tiled),
optionally ``sequence.gif`` or ``sequence.mp4`` (the RGB views in order, see
:mod:`regnf.compositor.sequence_io`), and ``render.json`` (cameras, settings, timings, field
evaluations per pixel: grid look-ups with the ``baked`` renderer, whose grids
:func:`~regnf.compositor.baked_composite.bake_for_views` bakes once for the views).

Nothing half-done is ever left in the folder: every camera is checked first (a camera
inside matter, or a view of more than :data:`MAX_PIXELS`, is refused before anything is
rendered), the views are written to a staging folder inside the output folder
(``.regnf-tmp-render-<random>``, see :mod:`regnf.core.output_dir`), and only when all of
them are done are they moved into place, ``render.json`` last. On any error the staging
folder is removed and the output folder is as it was.

The folder may hold other files (a replacement layer, a stage, the user's own): a render
never writes over or removes a file it did not write. Its files are the ones ``render.json``
lists; a file of the same name that no ``render.json`` lists (say the user's own
``rgb_0000.png``) makes the render refuse, and overwriting an earlier render
(``overwrite``) removes only the view and sequence files that render's ``render.json``
lists. While it writes, a render holds the folder's lock (``.regnf.lock``, a POSIX record
lock, see :mod:`regnf.core.file_lock`): a second render into the same folder at the same
time fails at once with :class:`regnf.core.file_lock.LockBusy`, and under the lock the
staging folders a killed render left behind are removed (nothing else is).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from regnf.core.atomic_io import write_json
from regnf.core.errors import RegnfError
from regnf.core.file_lock import folder_lock
from regnf.core.image_io import rgb_to_uint8, write_depth_png, write_instance_png, write_rgb_png
from regnf.core.output_dir import remove_leftovers, staging_dir, staging_prefix
from regnf.core.preflight import JsonInputError, read_json_input
from regnf.core.render_result import Render
from regnf.core.threads import map_one_thread_each, worker_count
from regnf.fields.distance_grid import DistanceGrid
from regnf.fields.field import Field
from regnf.fields.shading import check_camera_outside
from regnf.render.baked_field import BakeConfig
from regnf.render.camera import Camera
from regnf.render.sphere_render import render_many
from regnf.render.sphere_tracer import SphereTracerConfig
from regnf.render.volume_renderer import VolumeRendererConfig, render_volume

from .baked_composite import bake_for_views, baked_tracing
from .contact_sheets import contact_sheet
from .sequence_io import SEQUENCE_FORMATS, require_mp4, write_sequence

RENDERERS = ("sphere", "volume", "baked")
"""The renderers :func:`render_views` can use."""
RENDER_JSON = "render.json"
"""The report written last into the output folder."""
CONTACT_SHEET = "contact_sheet.png"
"""The RGB views tiled on one image."""
VIEW_FILE_RE = re.compile(r"^(rgb|depth|instance)_\d{4,}\.png$")
"""Per-view files this module writes (older ones are removed when overwriting)."""
SEQUENCE_STEM = "sequence"
"""The RGB views in order: ``sequence.gif`` or ``sequence.mp4``."""
SEQUENCE_FILE_RE = re.compile(r"^sequence\.(gif|mp4)$")
"""Sequence files this module writes (one of another format is removed when overwriting)."""
STAGING_LABEL = "render"
"""Label of the staging folders (``.regnf-tmp-render-*``), so that only a render's own leftovers are removed."""
MAX_PIXELS = 4096 * 4096
"""Most pixels one view may have (4096 x 4096, 16.8 megapixels). A view is rendered and kept
whole in memory (colour, depth, instance ids, per-pixel counters: about 40 bytes a pixel,
0.7 GB at this size, before the renderer's own working memory), so a larger size fails
only after minutes of work, or takes the machine's memory; it is refused before anything is
rendered."""
TRACE_PIXELS = 1 << 20
"""Most pixels of views traced together (:attr:`RenderConfig.views_per_trace`): 21 views of
256 x 192; a view of more is traced alone. Bounds the working memory a batch adds."""


@dataclass(frozen=True)
class RenderConfig:
    """How :func:`render_views` renders and writes.

    The batches of ``views_per_trace`` views render side by side on ``workers`` threads; the
    images are the same on any count (a lone batch, too, renders on one thread), and a view's
    ``seconds`` in ``render.json`` is its batch's wall time shared among the batch's views (with
    two workers, that of a batch sharing the machine)."""

    renderer: Literal["sphere", "volume", "baked"] = "sphere"
    """``sphere`` tracer, NeuS ``volume``, or tracer on ``baked`` grids (docs/decisions/rendering-speed.md)."""
    sphere: SphereTracerConfig = field(default_factory=lambda: SphereTracerConfig(footprint_fraction=0.05))
    """Sphere tracer settings: hits to 5 % of a pixel's footprint (docs/decisions/rendering-speed.md)."""
    volume: VolumeRendererConfig = field(default_factory=VolumeRendererConfig)
    """Settings of the volume renderer."""
    bake: BakeConfig = field(default_factory=BakeConfig)
    """Grids of the ``baked`` renderer."""
    sheet_columns: int = 0
    """Tiles per row of the contact sheet; 0: about square."""
    sheet_tile_width: int = 192
    """Largest width of a contact-sheet tile, pixels."""
    sequence: Literal["none", "gif", "mp4"] = "none"
    """Also write the RGB views in order as ``sequence.gif`` or ``sequence.mp4`` (one image size needed)."""
    sequence_fps: float = 10.0
    """Frames per second of the sequence."""
    overwrite: bool = False
    """Render into a folder that already holds a render (its old view files are replaced)."""
    progress: bool = True
    """Show a progress bar."""
    views_per_trace: int = 3
    """Views traced in one wavefront, :data:`TRACE_PIXELS` pixels at most (docs/decisions/rendering-speed.md)."""
    workers: int | None = None
    """Batches of views rendered side by side, one CPU thread each; None: one per usable core."""

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise RegnfError(f"workers must be >= 1, got {self.workers}")
        if self.views_per_trace < 1:
            raise RegnfError(f"views_per_trace must be >= 1, got {self.views_per_trace}")
        if self.renderer not in RENDERERS:
            raise RegnfError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        if self.sequence not in SEQUENCE_FORMATS:
            raise RegnfError(f"sequence must be one of {SEQUENCE_FORMATS}, got {self.sequence!r}")
        if not (math.isfinite(self.sequence_fps) and self.sequence_fps > 0):
            raise RegnfError(f"sequence_fps must be finite and > 0, got {self.sequence_fps}")

    @property
    def sequence_name(self) -> str | None:
        """``sequence.gif`` or ``sequence.mp4``, None without a sequence."""
        return None if self.sequence == "none" else f"{SEQUENCE_STEM}.{self.sequence}"


class ViewFiles(NamedTuple):
    """The files of one view, relative to the output folder."""

    rgb: str
    """8-bit RGB PNG."""
    depth: str
    """16-bit millimetre depth PNG (0: no hit)."""
    instance: str
    """16-bit instance PNG: instance id, 0 background."""


class RenderReport(NamedTuple):
    """What :func:`render_views` wrote."""

    out: Path
    """The output folder."""
    views: list[ViewFiles]
    """Per camera, in order."""
    json_path: Path
    """``render.json``."""
    seconds: list[float]
    """Render time per view (tracing, shading and writing), seconds."""
    evals_per_pixel_mean: float
    """Field evaluations per pixel over all views (composite costs included)."""
    sequence: Path | None = None
    """``sequence.gif`` or ``sequence.mp4``, None without a sequence."""


def view_files(k: int) -> ViewFiles:
    """File names of view ``k``."""
    return ViewFiles(f"rgb_{k:04d}.png", f"depth_{k:04d}.png", f"instance_{k:04d}.png")


def camera_json(camera: Camera) -> dict:
    """A camera as JSON: OpenCV axes, metres, pixel centres at ``u + 0.5``."""
    return {
        "K": camera.K.tolist(),
        "width": camera.width,
        "height": camera.height,
        "camera_to_world": camera.camera_to_world.tolist(),
    }


def jsonable(value: Any) -> Any:
    """``value`` with tuples as lists and non-finite floats as None (strict JSON)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def check_image_size(width: int, height: int, what: str = "a view") -> None:
    """Refuse (``ValueError``) an image of more than :data:`MAX_PIXELS` pixels."""
    if width * height > MAX_PIXELS:
        raise RegnfError(f"{what} of {width} x {height} pixels is more than the {MAX_PIXELS:,} pixels "
                         f"(4096 x 4096) a view may have; render smaller views")


def check_cameras(field: Field, cameras: Sequence[Camera]) -> None:
    """Refuse (``ValueError`` naming the camera) a camera whose image is too large or whose centre is inside matter."""
    for k, cam in enumerate(cameras):  # sizes first: cheap, and before any field query
        if not isinstance(cam, Camera):
            raise TypeError(f"cameras[{k}] must be a Camera, got {type(cam).__name__}")
        check_image_size(cam.width, cam.height, f"camera {k}: a view")
    world_to_field = np.linalg.inv(field.to_world.detach().cpu().double().numpy())
    for k, cam in enumerate(cameras):  # one SDF query per camera
        origin = world_to_field[:3, :3] @ cam.center + world_to_field[:3, 3]
        try:
            check_camera_outside(field, torch.as_tensor(origin))
        except ValueError as exc:
            raise RegnfError(f"camera {k} at {np.round(cam.center, 4).tolist()} m: {exc}") from exc


def check_sequence(cameras: Sequence[Camera], config: RenderConfig) -> None:
    """Refuse a sequence that cannot be written: views of different sizes, MP4 without its package.

    Raises
    ------
    ValueError
        Cameras of different image sizes.
    regnf.compositor.sequence_io.SequenceBackendError
        An MP4 sequence without ``imageio-ffmpeg`` (an ``ImportError``).
    """
    if config.sequence == "none":
        return
    sizes = sorted({(c.width, c.height) for c in cameras})
    if len(sizes) > 1:
        raise RegnfError(f"a {config.sequence} sequence needs views of one size, the cameras have "
                         f"{', '.join(f'{w} x {h}' for w, h in sizes)}")
    if config.sequence == "mp4":
        require_mp4()


def view_batches(cameras: Sequence[Camera], views_per_trace: int) -> list[list[int]]:
    """The views traced together (:attr:`RenderConfig.views_per_trace`): consecutive camera
    indices, at most ``views_per_trace`` and :data:`TRACE_PIXELS` pixels a batch (a larger view alone)."""
    batches: list[list[int]] = []
    pixels = 0
    for k, cam in enumerate(cameras):
        size = cam.width * cam.height
        if batches and len(batches[-1]) < views_per_trace and pixels + size <= TRACE_PIXELS:
            batches[-1].append(k)
            pixels += size
        else:
            batches.append([k])
            pixels = size
    return batches


def render_batch(field: Field, cameras: Sequence[Camera], config: RenderConfig,
                 grid: DistanceGrid | None) -> list[Render]:
    """Views with the configured renderer: the sphere tracer's in one wavefront (``grid`` for it)."""
    if config.renderer == "volume":
        return [render_volume(field, camera, config.volume) for camera in cameras]
    # The folder keeps no normals: their SDF gradients are not computed.
    return render_many(field, cameras, config.sphere, grid, normals=False)


def render_views(
    field: Field,
    cameras: Sequence[Camera],
    out: str | os.PathLike,
    config: RenderConfig = RenderConfig(),
    metadata: Mapping[str, Any] | None = None,
) -> RenderReport:
    """Render ``field`` from every camera into ``out`` (see the module for the files).

    Parameters
    ----------
    field : Field
        Any field (a composite reports instance ids and its full cost).
    cameras : sequence of Camera
        Posed in the field's metres; at least one.
    out : str or PathLike
        Output folder (created if needed).
    config : RenderConfig
    metadata : mapping, optional
        Extra JSON-serialisable entries for ``render.json`` (stage, mode, instance ids...).

    Raises
    ------
    ValueError
        No camera, a camera inside matter, a view of more than :data:`MAX_PIXELS` pixels,
        an output folder that already holds a render (unless ``overwrite``), a file in the
        way that no earlier render there wrote, non-finite field values, a sequence of
        views of different sizes; nothing is written then.
    regnf.compositor.sequence_io.SequenceBackendError
        An MP4 sequence without its package (an ``ImportError``); nothing is written then.
    regnf.core.file_lock.LockBusy
        Another process is rendering into ``out`` now (a ``RuntimeError``); nothing is written.
    """
    if len(cameras) == 0:
        raise RegnfError("nothing to render: no camera")
    out = Path(out)
    planned = _planned_files(len(cameras), config)
    _check_folder(out, planned, config)  # before anything is made: a refusal leaves no trace
    check_sequence(cameras, config)
    check_cameras(field, cameras)
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out, "the render folder"):
        _check_folder(out, planned, config)  # again: another render may have finished meanwhile
        remove_leftovers(out, staging_prefix(STAGING_LABEL))
        with staging_dir(out, STAGING_LABEL) as staging:  # removed on any error
            report = _render_into(field, cameras, out, staging, config, dict(metadata or {}))
            _commit(staging, out, report.views, config)
    return report


def _planned_files(n_views: int, config: RenderConfig) -> list[str]:
    """The files a render of ``n_views`` views writes, ``render.json`` last."""
    names = [name for k in range(n_views) for name in view_files(k)]
    return names + [CONTACT_SHEET] + ([config.sequence_name] if config.sequence_name else []) + [RENDER_JSON]


def recorded_files(out: str | os.PathLike) -> set[str]:
    """The files the ``render.json`` of ``out`` says its render wrote (empty without a readable one).

    Only names this module writes count (a view, the contact sheet, a sequence, ``render.json``),
    so an edited ``render.json`` cannot make a render remove anything else.
    """
    try:
        data = read_render_json(out)
    except ValueError:
        return set()
    listed = [RENDER_JSON]
    views = data.get("views") if isinstance(data, dict) else None
    for view in views if isinstance(views, list) else []:
        if isinstance(view, dict):
            listed += [view.get(key) for key in ViewFiles._fields]
    files = data.get("files") if isinstance(data, dict) else None
    if isinstance(files, dict):
        listed += [files.get("contact_sheet"), files.get("sequence")]
    return {name for name in listed if isinstance(name, str) and (
        name in (RENDER_JSON, CONTACT_SHEET) or VIEW_FILE_RE.match(name) or SEQUENCE_FILE_RE.match(name))}


def _check_folder(out: Path, planned: Sequence[str], config: RenderConfig) -> None:
    """Refuse a folder that holds a render (unless overwriting) or a file in the way that is not a render's."""
    if (out / RENDER_JSON).exists() and not config.overwrite:
        raise RegnfError(f"{out} already holds a render ({RENDER_JSON}); overwrite it explicitly")
    ours = recorded_files(out) if config.overwrite else set()
    clash = [name for name in planned if os.path.lexists(out / name) and name not in ours]
    if clash:
        raise RegnfError(f"{out / clash[0]}: exists and was not written by a render into this folder (no "
                         f"{RENDER_JSON} there lists it); move it away, or render into another folder")


def _render_into(
    field: Field,
    cameras: Sequence[Camera],
    out: Path,
    staging: Path,
    config: RenderConfig,
    metadata: dict,
) -> RenderReport:
    t_start = time.perf_counter()
    t_bake = 0.0
    if config.renderer == "baked":
        baked = bake_for_views(field, cameras, config.bake, progress=config.progress)
        field, t_bake = baked.field, baked.seconds
        config = dataclasses.replace(config, sphere=baked_tracing(config.sphere))
    grid = None
    if config.renderer in ("sphere", "baked") and config.sphere.grid_resolution > 0:
        s = config.sphere
        grid = DistanceGrid.build(field, s.grid_resolution, s.grid_lipschitz, s.chunk)
    t_grid = time.perf_counter() - t_start - t_bake
    views, seconds, stats, thumbs = [], [], [], []
    total_evals, total_pixels = 0, 0
    bar = tqdm(total=len(cameras), desc=f"render {len(cameras)} views", unit="view", disable=not config.progress)

    def timed(batch: list[int]) -> list[tuple[Render, float]]:
        t0 = time.perf_counter()
        renders = render_batch(field, [cameras[k] for k in batch], config, grid)
        took = (time.perf_counter() - t0) / len(batch)  # the batch's time, shared by its views
        return [(r, took) for r in renders]

    # Batches of views side by side, one CPU thread each (each batch is vectorised over its
    # pixels; the 3-D grid look-ups run on one thread whatever torch's setting, so one batch
    # on two threads leaves a core idle much of the time); as many at a time as there are
    # workers, each written before the next ones start, so that memory holds that many, not all.
    batches = view_batches(cameras, config.views_per_trace)
    chunk = worker_count(config.workers)
    rendered = (view for start in range(0, len(batches), chunk)
                for batch in map_one_thread_each(timed, batches[start:start + chunk], chunk)
                for view in batch)
    for k, (cam, (r, took)) in enumerate(zip(cameras, rendered)):
        bar.update(1)
        t_write = time.perf_counter()
        names = view_files(k)
        rgb8 = rgb_to_uint8(r.rgb)
        write_rgb_png(staging / names.rgb, rgb8)
        write_depth_png(staging / names.depth, r.depth, r.mask)
        write_instance_png(staging / names.instance, r.instance_id)
        thumbs.append(rgb8)
        seconds.append(took + time.perf_counter() - t_write)  # rendering and writing
        evals = int(r.evals_per_pixel.sum())
        total_evals += evals
        total_pixels += cam.width * cam.height
        ids = r.instance_id.detach().cpu()
        stats.append({
            "index": k,
            **names._asdict(),
            "seconds": seconds[-1],
            "evals_per_pixel_mean": evals / (cam.width * cam.height),
            "lookups_per_pixel_mean": float(r.lookups_per_pixel.double().mean()),
            "hit_fraction": float(r.mask.double().mean()),
            "instance_pixels": {str(int(i)): int(c) for i, c in zip(*torch.unique(ids, return_counts=True))},
        })
        views.append(names)
    bar.close()
    sheet = contact_sheet(thumbs, config.sheet_columns, config.sheet_tile_width)
    write_rgb_png(staging / CONTACT_SHEET, sheet)
    if config.sequence_name is not None:
        write_sequence(staging / config.sequence_name, thumbs, config.sequence, config.sequence_fps)
    epp = total_evals / total_pixels
    asdict = dataclasses.asdict
    settings = {"volume": asdict(config.volume), "sphere": asdict(config.sphere),
                "baked": {"sphere": asdict(config.sphere), "bake": asdict(config.bake)}}[config.renderer]
    payload = {
        **metadata,
        "renderer": config.renderer,
        "renderer_config": settings,
        "field": {"name": field.name, "label": field.label, "to_world": field.to_world.tolist()},
        "files": {
            "depth_png": "uint16 millimetres of z-depth along the optical axis, 0 = no hit",
            "instance_png": "uint16 instance id i >= 1 where instance i is seen, 0 background and scene",
            "contact_sheet": CONTACT_SHEET,
            "sequence": config.sequence_name,
            "sequence_fps": config.sequence_fps if config.sequence_name else None,
        },
        "cameras": [camera_json(c) for c in cameras],
        "views": stats,
        "evals_per_pixel_mean": epp,
        "timings": {
            "bake_seconds": t_bake,
            "distance_grid_seconds": t_grid,
            "render_seconds_total": float(sum(seconds)),
            "per_view_seconds_mean": float(np.mean(seconds)),
            "total_seconds": time.perf_counter() - t_start,
        },
    }
    write_json(staging / RENDER_JSON, jsonable(payload))
    sequence = out / config.sequence_name if config.sequence_name else None
    return RenderReport(out, views, out / RENDER_JSON, seconds, epp, sequence)


def _commit(staging: Path, out: Path, views: list[ViewFiles], config: RenderConfig) -> None:
    """Move the staged files into ``out`` (``render.json`` last); drop the earlier render's stale files.

    Stale files are the views and the sequence that the earlier ``render.json`` lists and
    this render does not write (it had more views, or another sequence format); nothing
    that no ``render.json`` lists is removed.
    """
    new = {name for v in views for name in v}
    extra = [CONTACT_SHEET] + ([config.sequence_name] if config.sequence_name else [])
    earlier = recorded_files(out) if config.overwrite else set()
    for name in sorted(new) + extra + [RENDER_JSON]:
        os.replace(staging / name, out / name)
    staging.rmdir()
    for name in sorted(earlier - new - set(extra) - {RENDER_JSON, CONTACT_SHEET}):
        (out / name).unlink(missing_ok=True)


def read_render_json(out: str | os.PathLike) -> dict:
    """The ``render.json`` of a render folder."""
    path = Path(out) / RENDER_JSON
    try:
        return read_json_input(path, None, "render report")
    except JsonInputError as exc:
        raise RegnfError(f"{path}: cannot read the render report ({exc.problem})") from exc
