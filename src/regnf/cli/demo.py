"""The end-to-end demo: from a synthetic capture to a USD stage, composites and a report.

:func:`run_demo` runs every step of the tool on one ONR-like room:

1. capture the room (RGB-D, low coverage: its objects are seen from few sides) and make its
   library objects (distilled from their meshes);
2. train the room's scene field (both cached: a second run reuses them);
3. write a USD stage with the scene field and the library;
4. discover the library's objects in the scene field with no boxes and register them; each is
   measured against the ground-truth pose, and the identified ones become instances;
5. bake the scene less its instances and every library object into grids for the orbit's
   pixel footprint (kept in the cache under ``baked/<room>-<coverage>-<library source>/``:
   a second run reads them);
6. render the scene field alone around the room through its network (a room's grid cell
   loses the thin parts of the chairs the scene field holds), and with every instance
   substituted by its library field on the grids; per object, both through the networks from a
   side the capture never saw (next to the ground-truth render: object completion);
7. render two random instance replacements on the grids;
8. export the stage as one ``.usdz`` for other tools (:data:`DEMO_EXPORT`): the scene less the
   substituted instances meshed in, every library object's source mesh with its materials,
   rigid bodies and colliders;
9. write ``report.html`` with every image, the registration table, loss curves and timings.

Layout of ``out``::

    report.html, report/           the report (open it in a browser)
    summary.json                   everything the report shows, as numbers
    stage/<room>.usda + assets     the stage; registration/<instance>.json per registration
    <room>.usdz                    the same stage as one package, the edit meshed in
    renders/scene/, renders/substitute/   orbit views (contact_sheet.png, sequence.gif, ...)
    renders/completion.png         per object: ground truth | scene field | substituted
    replacements/seed_1/, seed_2/  random replacements (replacement.usda, views, transforms.json)
    .regnf-output.json, .regnf.lock   the marker of a demo folder and its lock (regnf.core.output_dir)

The folder is the demo's own: a new or empty one, or one an earlier demo made (the marker
lists what it made). Anything else is refused before any work, unless ``reuse`` is set; even
then, an entry of the names above that the demo did not make is refused rather than written
over. Each run replaces only what the marker says the demo made, and holds the folder's lock
while it runs, so two demos into one folder do not mix.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import os
import platform
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch
from rich.console import Console

from regnf.compositor.tool_export import ToolExportConfig
from regnf.registration.metrics import BARS
from regnf.synthetic.cache import Cache, default_cache_dir

if TYPE_CHECKING:
    from regnf.captures.model import Capture
    from regnf.compositor.baked_composite import BakedGrids
    from regnf.core.output_dir import OutputFolder
    from regnf.render.camera import Camera
    from regnf.scene_graph.validation import ValidationReport
    from regnf.synthetic.rooms import Room

console = Console(stderr=True)

THRESHOLDS = {"rot_geodesic_rad": BARS["rot_geodesic_sym_rad"], "trans_rel_diag": BARS["trans_rel_diag_sym"],
              "scale_rel": BARS["scale_rel"]}
"""Acceptance targets of a registration against ground truth: the benchmark's bars, under the
names of the demo's rows (whose errors are the symmetry-aware ones)."""



@dataclass(frozen=True)
class DemoConfig:
    """What the demo makes."""

    room: Literal["ac-room", "atbl-room", "mix-room"] = "ac-room"
    """The room: its objects are the library."""
    coverage: Literal["low", "full"] = "low"
    """Capture trajectory of the room (low: objects seen from few sides, the completion case)."""
    library_source: Literal["mesh", "rgbd"] = "mesh"
    """Library fields distilled from the objects' meshes (fast) or trained from their RGB-D captures."""
    orbit_views: int = 6
    """Views on an orbit around the room, for the scene, the substitution and each replacement."""
    width: int = 256
    """Image width of the renders."""
    height: int = 192
    """Image height of the renders."""
    replacement_seeds: tuple[int, ...] = (1, 2)
    """Seeds of the random replacements."""
    completion_box_pad: float = 0.25
    """Growth of each removal box (a low-coverage field smears objects into space it never saw;
    docs/benchmarks.md, "Rendering and object completion")."""
    device: str = "cpu"
    """Torch device."""
    reuse: bool = False
    """Write into an --out folder that holds files the demo did not make (they are kept; an entry
    of the demo's own names that it did not make, such as stage/, is still refused)."""


DEMO_KIND = "demo"
"""Kind of command recorded in the demo folder's marker."""
GRIDS_DIR = "baked"
"""Folder of the cache that holds the demo stages' baked grids (:func:`regnf.datasets.data_set_grids.cached_stage_grids`)."""
DEMO_EXPORT = ToolExportConfig(library_cell=0.0)
"""The export the demo writes: the library objects' source meshes render, so their fields' proxies
stay the stage's (colliders and the proxy purpose)."""
REMADE = ("stage", "renders", "replacements", "report")
"""Folders of ``out`` made again from scratch on every run (an earlier demo's are removed)."""


def demo_entries(config: DemoConfig) -> list[str]:
    """The top-level entries a demo run writes in its output folder."""
    return [*REMADE, "report.html", "summary.json", f"{config.room}.usdz"]


@contextlib.contextmanager
def demo_folder(out: str | Path, config: DemoConfig) -> Iterator[OutputFolder]:
    """Claim ``out`` for the demo and hold its lock for the block; yield it with the demo's entries reserved.

    The run then removes an earlier demo's :data:`REMADE` folders with ``folder.remove``
    (only those the marker records as the demo's).

    Raises
    ------
    regnf.core.output_dir.OutputFolderError
        ``out`` holds files the demo did not make (and ``config.reuse`` is off), or an entry
        of the demo's names that it did not make; nothing is written then.
    regnf.core.file_lock.LockBusy
        Another demo is running into ``out``.
    """
    from regnf.core.output_dir import inspect_output_dir, owned_output_dir

    path = Path(out).absolute()
    # Everything is checked before anything is written: a refused folder gets no marker and no lock file.
    inspect_output_dir(path, DEMO_KIND, config.reuse).require_free(demo_entries(config))
    with owned_output_dir(path, DEMO_KIND, config.reuse, "the demo folder") as folder:
        yield folder.reserve(demo_entries(config))


class StepLog:
    """Times the demo's steps and tells, from the cache folder, whether each made anything."""

    def __init__(self, cache_root: Path) -> None:
        self.cache_root = cache_root
        self.steps: list[dict[str, Any]] = []

    def _entries(self) -> set[str]:
        return {str(p) for sub in ("captures", "fields") for p in (self.cache_root / sub).glob("*")}

    @contextlib.contextmanager
    def step(self, name: str, detail: str = "", cacheable: bool = False) -> Iterator[dict[str, Any]]:
        """Time the block; ``cacheable`` steps are marked cached when they added nothing to the cache."""
        console.print(f"[bold cyan]>[/] {name}" + (f" ({detail})" if detail else ""))
        before = self._entries() if cacheable else set()
        record: dict[str, Any] = {"name": name, "detail": detail}
        t0 = time.perf_counter()
        yield record
        record["seconds"] = time.perf_counter() - t0
        # A block may say itself whether it made anything (what it reused may be checked and kept).
        record.setdefault("cached", bool(cacheable and self._entries() == before))
        self.steps.append(record)
        console.print(f"  {record['seconds']:.1f} s" + (" (cached)" if record["cached"] else ""))


def machine() -> dict[str, Any]:
    """Where the demo ran."""
    return {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version(), "platform": platform.platform()}


def _discover_all(stage: Path, out: Path, scene_path: Path, library_paths: dict[str, Path],
                  capture: Capture, device: str) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Discover the library's objects in the scene field with no boxes; write the identified ones
    to the stage; compare every true instance with what became of it.

    Returns one row per true instance (its errors when the right object was identified) and a
    summary of the discovery: candidates, false instances, seconds, the top view.
    """
    from regnf.core.atomic_io import write_json
    from regnf.fields.oriented_box import OrientedBox
    from regnf.io.checkpoint import load_field
    from regnf.registration.discovery import FieldFiles, discover
    from regnf.registration.discovery_records import instance_payloads
    from regnf.registration.discovery_view import draw_top_view
    from regnf.scene_graph import add_instance_from_registration
    from regnf.synthetic.ground_truth import score_discovery

    scene = load_field(scene_path, device=device)
    library = {name: load_field(p, device=device) for name, p in library_paths.items()}
    result = discover(scene, library, progress=True, files=FieldFiles(scene_path, dict(library_paths)))
    written: dict[int, tuple[str, str]] = {}
    for index, payload in instance_payloads(result, scene, library, scene_path, library_paths):
        rel = f"registration/candidate_{index}.json"
        write_json(out / rel, payload)
        written[index] = (add_instance_from_registration(stage, payload), rel)
    scores, false, matched = score_discovery(result, capture.instances, scene, library)
    rows = []
    for i, (inst, score) in enumerate(zip(capture.instances, scores)):  # a handful of objects
        d = result.discoveries[matched[i]] if i in matched else None
        row: dict[str, Any] = {
            "instance": inst.id, "object": inst.library, "label": library[inst.library].label,
            "box_iou": score["iou"], "found_as": "not found", "stage_instance": None,
            "accepted": False, "confidence": None, "rot_geodesic_rad": None, "trans_m": None,
            "trans_rel_diag": None, "scale_rel": None, "within_bars": False, "seconds": None, "history": [],
        }
        if d is not None and d.skipped is not None:
            row["found_as"] = f"skipped: {d.skipped}"
        elif d is not None:
            row["found_as"] = (d.chosen.library_name if d.chosen is not None else
                               f"ambiguous: {' or '.join(d.ambiguous)}" if d.ambiguous else "unmatched")
            row["confidence"] = score["right_object_confidence"]
        if score["identified"]:
            row.update({k: score[k] for k in ("confidence", "rot_geodesic_rad", "trans_m", "trans_rel_diag",
                                              "scale_rel", "within_bars")})
            row.update({
                "stage_instance": written[matched[i]][0], "registration_file": written[matched[i]][1],
                "accepted": True,
                # The object's full registration in the candidate's box and the refit (not the
                # short registrations, shared by every object of the candidate).
                "seconds": sum(t.result.timings.get("total", 0.0) for t in d.tried
                               if t.library_name == inst.library and t.result is not None)
                + d.chosen.result.timings.get("total", 0.0),
                "history": d.chosen.result.history,
            })
            console.print(f"  {inst.id}: found as {row['found_as']}, confidence {row['confidence']:.2f}, rotation "
                          f"{np.degrees(row['rot_geodesic_rad']):.2f} deg, translation "
                          f"{100 * row['trans_rel_diag']:.2f} % of its size, scale {100 * row['scale_rel']:.2f} %")
        else:
            console.print(f"  {inst.id}: {row['found_as']} (box IoU {row['box_iou']:.2f})")
        rows.append(row)
    false = [f"{f['chosen']} in candidate {f['candidate']}" for f in false]
    truth_boxes = [OrientedBox.from_corners(inst.box_corners) for inst in capture.instances]
    image = draw_top_view(result, out / "top_view.png",
                          [(inst.library, box) for inst, box in zip(capture.instances, truth_boxes)],
                          title="discovery: the room from above")
    return rows, {"candidates": len(result.discoveries), "identified": len(result.instances),
                  "unmatched": len(result.unmatched), "skipped": [d.skipped for d in result.skipped],
                  "false_instances": false, "seconds": result.seconds,
                  "image": str(image)}


def _completion(stage: Path, room: Room, config: DemoConfig, out: Path) -> dict[str, Any]:
    """Per object, one view from a side the capture never saw: truth | scene field | substituted."""
    from regnf.compositor.from_stage import composite_from_stage
    from regnf.compositor.render_folder import RenderConfig, view_batches
    from regnf.compositor.stage_config import StageCompositeConfig
    from regnf.core.image_io import rgb_to_uint8, write_rgb_png
    from regnf.core.threads import map_one_thread_each
    from regnf.fields.distance_grid import DistanceGrid
    from regnf.render.evaluation import psnr
    from regnf.render.sphere_render import render_many
    from regnf.synthetic.unseen_views import reference_renderer, unseen_cameras

    sphere = RenderConfig().sphere
    fields = {mode: composite_from_stage(stage, StageCompositeConfig(mode=mode, box_pad=config.completion_box_pad),
                                         config.device).field for mode in ("scene", "substitute")}
    grids = {m: DistanceGrid.build(f, sphere.grid_resolution, sphere.grid_lipschitz) for m, f in fields.items()}
    meshes = room.instance_meshes()
    views = []  # (instance index, camera, ground truth)
    with reference_renderer(room) as ref:  # OpenGL: on this thread
        for k in range(len(room.instances)):  # one view per object
            cams = unseen_cameras(room, meshes[k].bounds.mean(axis=0), 1, free=fields["scene"])
            if cams:
                views.append((k, cams[0], ref.render(cams[0].camera_to_world, cams[0].K)))
    modes = ("scene", "substitute")
    # Batches of views traced together (as render_views does), side by side, one thread each:
    # the bits of one after another (regnf.core.threads).
    cams = [cam for _, cam, _ in views]
    jobs = [(m, batch) for m in modes for batch in view_batches(cams, RenderConfig().views_per_trace)]
    batches = map_one_thread_each(lambda job: [r.rgb.detach().cpu().numpy() for r in render_many(
        fields[job[0]], [cams[j] for j in job[1]], sphere, grid=grids[job[0]], normals=False)], jobs)
    rendered = {(m, j): rgb for (m, idx), imgs in zip(jobs, batches) for j, rgb in zip(idx, imgs)}
    rows, per_object = [], []
    for j, (k, _, gt) in enumerate(views):
        gt_rgb, region = rgb_to_uint8(gt.rgb), gt.instance_id.numpy() == k
        row, scores = [gt_rgb], {}
        for mode in modes:
            rgb = rendered[mode, j]
            scores[mode] = psnr(rgb[region], gt_rgb[region] / 255.0) if region.any() else float("nan")
            row.append(rgb_to_uint8(rgb))
        rows.append(np.concatenate(row, axis=1))
        inst = room.instances[k]
        per_object.append({"instance": inst.id, "object": inst.library,
                           "psnr_scene": scores["scene"], "psnr_substitute": scores["substitute"]})
    path = out / "renders" / "completion.png"
    write_rgb_png(path, np.concatenate(rows, axis=0))
    return {"image": str(path.relative_to(out)), "objects": per_object}


def _orbit_cameras(stage: Path, config: DemoConfig) -> list[Camera]:
    """The orbit around the scene field's bounds that the scene, substitution and replacements share."""
    from regnf.compositor.cameras_io import OrbitConfig, field_bounds_metres, orbit_around_bounds
    from regnf.compositor.from_stage import composite_from_stage
    from regnf.compositor.stage_config import StageCompositeConfig

    scene = composite_from_stage(stage, StageCompositeConfig(mode="scene"), config.device).field.scene
    orbit = OrbitConfig(n=config.orbit_views, width=config.width, height=config.height)
    return orbit_around_bounds(field_bounds_metres(scene), orbit)


def _render_mode(stage: Path, mode: str, cameras: list[Camera], out: Path,
                 config: DemoConfig, grids: BakedGrids | None = None) -> dict[str, Any]:
    """Render the stage's composite in ``mode`` into ``out`` (on ``grids``, the masked scene's and
    the objects', when given); its speed."""
    from regnf.compositor.baked_composite import with_object_grids
    from regnf.compositor.from_stage import composite_from_stage
    from regnf.compositor.render_folder import RenderConfig, render_views
    from regnf.compositor.stage_config import StageCompositeConfig

    comp = composite_from_stage(stage, StageCompositeConfig(mode=mode, box_pad=config.completion_box_pad),
                                config.device)
    field, render = comp.field, RenderConfig(sequence="gif", overwrite=True)
    if grids is not None:
        field = with_object_grids(comp, {i: r.library_name for i, r in comp.scene.instances.items()}, grids)
        render = dataclasses.replace(render, renderer="baked")
    report = render_views(field, cameras, out, render, {"stage": str(stage), "mode": mode,
                                                          "instance_ids": comp.instance_ids})
    return {"seconds_per_view": float(np.mean(report.seconds)), "evals_per_pixel": report.evals_per_pixel_mean,
            "renderer": render.renderer}


def run_demo(out: str | Path = Path("out/demo"), config: DemoConfig = DemoConfig(),
             cache: Cache | None = None) -> Path:
    """Run the demo into ``out`` (replacing an earlier demo there); return ``report.html``.

    ``out`` must be new, empty or an earlier demo's folder (or ``config.reuse`` set); see
    :func:`demo_folder`, which raises before any work if it is not.
    """
    with demo_folder(out, config) as folder:  # refused or locked before any work
        return _run_demo(folder, config, cache)


def _run_demo(folder: OutputFolder, config: DemoConfig, cache: Cache | None) -> Path:
    """The demo's steps, into the claimed and locked ``folder``."""
    from regnf.compositor.replace import ReplaceConfig, replace_and_render
    from regnf.compositor.stage_config import StageCompositeConfig
    from regnf.compositor.tool_export import export_for_tools
    from regnf.core.atomic_io import write_json
    from regnf.datasets.data_set_grids import cached_stage_grids
    from regnf.render.baked_field import BakeConfig
    from regnf.scene_graph import new_stage, validate_stage
    from regnf.synthetic.capture import RoomCaptureConfig
    from regnf.synthetic.rooms import ROOM_CONTENTS, make_room

    from .report import write_report

    t_start = time.perf_counter()
    out = folder.path
    cache = cache or Cache(default_cache_dir())
    log = StepLog(cache.root)
    names = ROOM_CONTENTS[config.room]
    capture_cfg = RoomCaptureConfig(coverage=config.coverage)

    with log.step("capture the room", f"{config.room}, {config.coverage} coverage", cacheable=True) as rec:
        capture = cache.room_capture(config.room, capture_cfg)
        rec["detail"] += f", {len(capture.frames)} RGB-D frames"
    with log.step("train the scene field", f"{config.room}, NeuS-style SDF from RGB-D", cacheable=True):
        scene_path = cache.scene_field(config.room, config.coverage, config.device)
    with log.step("make the library", f"{len(names)} objects from their {config.library_source}",
                  cacheable=True):
        library_paths = {n: cache.object_field(n, config.library_source, config.device) for n in names}

    # A fresh run: the stage, the renders and the report are remade (only the demo's own are removed).
    for sub in REMADE:
        folder.remove(sub)
    stage = out / "stage" / f"{config.room}.usda"
    with log.step("write the USD stage", "scene field and library, proxy meshes"):
        new_stage(stage, scene_path, [library_paths[n] for n in names],
                  provenance={"made_by": "regnf demo", "room": config.room, "coverage": config.coverage})
    with log.step("discover and register the objects", "no boxes: candidates from the field's surface, "
                  "a short registration of every library object in each, the best and any close behind fully registered"):
        registrations, discovery = _discover_all(stage, out / "stage", scene_path, library_paths, capture,
                                                 config.device)
    accepted = [r for r in registrations if r["accepted"]]
    if not accepted:
        raise RuntimeError("no registration was accepted: nothing to composite")

    cameras = _orbit_cameras(stage, config)
    substitute = StageCompositeConfig(mode="substitute", box_pad=config.completion_box_pad)
    with log.step("bake the grids", "the scene less the instances and every library object, for the orbit",
                  cacheable=True) as rec:
        grids, seconds = cached_stage_grids(cache.root / GRIDS_DIR, f"{config.room}-{config.coverage}-"
                                            f"{config.library_source}", stage, cameras, BakeConfig(),
                                            substitute, config.device, progress=True,
                                            on_wait=lambda why: console.print(f"  {why}"))
        rec["cached"] = seconds == 0.0
    renders = {}
    for mode, what in (("scene", "the scene field alone"), ("substitute", "instances substituted, on the grids")):
        with log.step(f"render {mode}", f"{len(cameras)} orbit views, {what}"):
            renders[mode] = _render_mode(stage, mode, cameras, out / "renders" / mode, config,
                                         grids if mode == "substitute" else None)
    room = make_room(config.room, seed=capture_cfg.seed)
    with log.step("render object completion", "one unseen view per object, against ground truth"):
        completion = _completion(stage, room, config, out)
    replacements = []
    for seed in config.replacement_seeds:
        with log.step(f"random replacement, seed {seed}", f"{len(cameras)} orbit views, on the grids"):
            cfg = ReplaceConfig(substitute, device=config.device)
            res = replace_and_render(stage, seed, out / "replacements" / f"seed_{seed}", cameras, cfg, grids=grids)
            replacements.append({"seed": seed, "selections": res.selections})
    usdz = out / f"{config.room}.usdz"
    with log.step("export the .usdz", "one self-contained package for other tools: the edit meshed in, "
                  "source meshes with their materials, physics"):
        export_for_tools(stage, [usdz], DEMO_EXPORT)
        validation = validate_stage(usdz)

    summary = _summary(config, out, stage, usdz, log, registrations, discovery, renders, completion,
                       replacements, validation, time.perf_counter() - t_start)
    write_json(out / "summary.json", summary)
    report = write_report(out, summary)
    console.print(f"[green]demo done[/] in {summary['total_seconds']:.0f} s: open {report}")
    console.print(f"look around and fix registrations in the viewer: regnf view {stage}")
    return report


def _summary(config: DemoConfig, out: Path, stage: Path, usdz: Path, log: StepLog, registrations: list,
             discovery: dict[str, Any], renders: dict, completion: dict, replacements: list, validation: ValidationReport,
             total: float) -> dict[str, Any]:
    """Everything the report shows (see :func:`regnf.cli.report.write_report` for the keys)."""
    rel = lambda p: str(Path(p).relative_to(out))
    objs = completion["objects"]
    gain = np.nanmean([o["psnr_substitute"] - o["psnr_scene"] for o in objs]) if objs else float("nan")
    per_obj = ", ".join(f"{o['instance']} {o['psnr_scene']:.1f} -> {o['psnr_substitute']:.1f} dB" for o in objs)
    sections = [
        {"title": "Discovery",
         "text": ("The room from above: the scene field's observed surface (grey), the candidates discovery "
                  "found (green: identified, with the library object and its confidence; red dashed: "
                  "unmatched) and the true boxes (black dotted), which discovery never saw."),
         "images": [{"path": rel(discovery["image"]), "caption": "discovery against the true boxes"}]},
        {"title": "Object completion",
         "text": (f"Each row is one object seen from a side the {config.coverage}-coverage capture never saw: "
                  f"ground truth | the scene field alone | the library object substituted at its registered "
                  f"pose. PSNR on the object's pixels: {per_obj} (mean gain {gain:+.1f} dB)."),
         "images": [{"path": completion["image"], "caption": "ground truth | scene field | substituted"}]},
        {"title": "Scene field and substitution around the room",
         "text": (f"{config.orbit_views} views on an orbit inside the room, {config.width}x{config.height}, sphere "
                  f"traced: the scene field alone through its network at {renders['scene']['seconds_per_view']:.2f} s "
                  f"per view ({renders['scene']['evals_per_pixel']:.1f} evaluations per pixel); the substitution, "
                  "like the replacements below, on grids baked once from the fields (cells of half a pixel's "
                  f"footprint, kept in the cache) at {renders['substitute']['seconds_per_view']:.2f} s per view."),
         "images": [{"path": "renders/scene/contact_sheet.png", "caption": "the scene field alone"},
                    {"path": "renders/substitute/contact_sheet.png",
                     "caption": "every registered instance substituted by its library field"},
                    {"path": "renders/substitute/sequence.gif", "caption": "the substitution, animated"}]},
        {"title": "Random instance replacement",
         "text": "Each instance swapped for a random library object of its class, standing where the "
                 "registered one stood: " + "; ".join(
                     f"seed {r['seed']}: " + ", ".join(f"{i} -> {n}" for i, n in sorted(r["selections"].items()))
                     for r in replacements),
         "images": [{"path": f"replacements/seed_{r['seed']}/contact_sheet.png", "caption": f"seed {r['seed']}"}
                    for r in replacements]},
    ]
    missed = [r for r in registrations if not r["accepted"]]
    note = (f"The room was captured with {config.coverage} coverage. No boxes were given: discovery found "
            f"{discovery['candidates']} candidates in the scene field, identified {discovery['identified']} of them "
            f"(a short registration of every library object in each, the best and any close behind fully registered) and left "
            f"{discovery['unmatched']} unmatched"
            + (f" and skipped {len(discovery['skipped'])} that could not be examined ({'; '.join(discovery['skipped'])})"
               if discovery.get("skipped") else "")
            + f", in {discovery['seconds']['total']:.0f} s; the errors are measured "
            f"against the true poses. {len(registrations) - len(missed)} of {len(registrations)} objects were found, "
            f"identified as the right library object and written to the stage; "
            f"{sum(r['accepted'] and r['within_bars'] for r in registrations)} of them are within the bars (rotation <= "
            f"{THRESHOLDS['rot_geodesic_rad']} rad, translation <= {100 * THRESHOLDS['trans_rel_diag']:g} % of "
            f"the object's diagonal, scale <= {100 * THRESHOLDS['scale_rel']:g} %). False instances: "
            + (", ".join(discovery["false_instances"]) or "none") + ".")
    if missed:
        note += (" Not written to the stage: " + ", ".join(f"{r['instance']} ({r['found_as']})" for r in missed)
                 + ". Leaving an object out instead of placing a wrong one is the intended behaviour.")
    if config.coverage == "low":
        note += (" The bars are the registration benchmark's (docs/benchmarks.md); a low-coverage field "
                 "shows each object from one or two sides only.")
    files = [{"path": rel(stage), "what": "the USD stage (open it in usdview or any USD tool)"},
             {"path": rel(usdz), "what": f"the stage as one package: {len(validation.validators)} OpenUSD "
              f"validators, {len(validation.errors)} errors"},
             {"path": "summary.json", "what": "every number of this report"}]
    files += [{"path": f"replacements/seed_{r['seed']}/transforms.json",
               "what": f"seed {r['seed']}: nerfstudio cameras, depth and instance masks"} for r in replacements]
    files += [{"path": f"stage/{r['registration_file']}", "what": f"registration of {r['instance']}"}
              for r in registrations if r.get("registration_file")]
    return {
        "title": f"regnf demo: {config.room}",
        "command": "regnf demo --out " + str(out),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {**machine(), "device": config.device},
        "total_seconds": total,
        "config": dataclasses.asdict(config),
        "steps": log.steps,
        "registrations": registrations,
        "thresholds": THRESHOLDS,
        "registration_note": note,
        "completion": completion,
        "renders": renders,
        "replacements": replacements,
        "usdz_validation": {"validators": len(validation.validators), "errors": validation.errors},
        "sections": sections,
        "files": files,
    }
