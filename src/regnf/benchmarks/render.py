"""Render benchmark: the sphere tracer against the NeuS-style volume renderer on the composite
ac-room, and object completion on the low-coverage ac-room.

References are pyrender renders of the ground-truth meshes from the same cameras (the
capture's own renderer: the images a field is trained on look the same). Registrations are
run, not taken from the ground truth: the composites are what a user gets.

- Speed rows: the full-coverage ac-room with every chair substituted by its registered library
  field, 256x192, from views of the full-coverage capture's test split; neural-field
  evaluations per pixel (the coarse distance grid's look-ups counted apart), seconds per frame,
  PSNR of the whole image against the reference. The ``baked`` row sphere-traces the same
  composite baked into grids (:mod:`regnf.compositor.baked_composite`; its evaluations are
  grid look-ups) and adds its PSNR against the neural render and the baking's time.
- Completion: the low-coverage ac-room (its capture only ever looks at the objects from the
  -y side), each chair rendered before (the scene field) and after substitution from 8 views on
  the +y side, which the capture never saw; PSNR and mean absolute depth error on the object's
  pixels in the reference (its instance mask).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from regnf.compositor import Camera, render, render_volume
from regnf.compositor.baked_composite import bake_for_views, baked_tracing
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.compositor.substitution import SubstitutedInstance, build_composite
from regnf.core.image_io import rgb_to_uint8
from regnf.fields.distance_grid import DistanceGrid
from regnf.fields.field import Field
from regnf.io.checkpoint import load_field
from regnf.meshes.meshing import extract_mesh
from regnf.registration.pipeline import register
from regnf.render.baked_field import BakeConfig
from regnf.render.evaluation import psnr, world_to_field
from regnf.render.sphere_tracer import SphereTracerConfig
from regnf.render.volume_renderer import VolumeRendererConfig
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.ground_truth import proposal_from_instance
from regnf.synthetic.render import RGBDRenderer
from regnf.synthetic.rooms import make_room
from regnf.synthetic.shading import shaded_copy
from regnf.synthetic.unseen_views import (
    DISTANCE,
    EYE_HEIGHT,
    HEIGHT,
    WIDTH,
    reference_renderer,
    unseen_cameras,
)

ROOM = "ac-room"
"""The room of both parts (the paper's completion example is a chair in it)."""


@dataclass(frozen=True)
class RenderBenchConfig:
    """Settings of :func:`run_render_benchmark`."""

    speed_views: int = 4
    """Views of the full-coverage test split rendered by both renderers."""
    completion_views: int = 8
    """Unseen views per object for the completion measurement."""
    completion_distance: float = DISTANCE
    """Distance of the completion cameras from the object's centre, metres (horizontal)."""
    completion_height: float = EYE_HEIGHT
    """Height of the completion cameras, metres."""
    sphere: SphereTracerConfig = field(default_factory=lambda: SphereTracerConfig(footprint_fraction=0.05))
    """The sphere tracer's settings: hits to 5 % of a pixel's footprint (the default, 1e-4, is
    for exact depth tests; measured here: 17.7 evaluations per pixel against 14.4, at the
    same PSNR against the reference, 32.6 and 32.5 dB)."""
    volume: VolumeRendererConfig = field(default_factory=VolumeRendererConfig)
    """The volume renderer's settings (the authors' 200 uniform samples per ray)."""
    bake: BakeConfig = field(default_factory=BakeConfig)
    """Grids of the ``baked`` row (the defaults: half a pixel's footprint, at most 2^25 nodes a
    field)."""
    completion_removal: StageCompositeConfig = field(
        default_factory=lambda: StageCompositeConfig(mode="substitute", box_pad=0.25))
    """Removal for completion: the proposal and the object's box grown by 25 %. A low-coverage
    field smears an object into the space behind it that it never saw; measured (mean over the
    5 chairs, PSNR gain / depth error ratio): box_pad 0.05: +5.0 dB / 0.45, 0.25: +5.8 dB /
    0.35, 0.4: +6.1 dB / 0.31 (a larger box also cuts more of the neighbourhood)."""
    remnant_tolerance: float = 0.05
    """A removed object's pixel that shows the scene more than this (metres) in front of the
    empty room counts as a remnant."""
    matched_footprint_fraction: float = 0.3
    """Hit tolerance of the ``sphere-matched`` row, which trades the sphere tracer's extra
    quality for fewer evaluations until its PSNR is that of the volume renderer."""


def substituted_composite(scene: Field, library: dict[str, Field], instances: Sequence,
                          progress: bool = False,
                          composite: StageCompositeConfig | None = None,
                          ) -> tuple[Field, list[dict]]:
    """``scene`` with each instance whose library object is in ``library`` registered (with its
    true box as the proposal, the paper's assumption) and substituted. Returns the composite
    and one record per registration (confidence, seconds)."""
    S = scene.to_world.detach().cpu().double().numpy()
    specs, records = [], []
    for inst in tqdm(instances, desc="register", disable=not progress):
        lib = library.get(inst.library)
        if lib is None:
            continue
        t0 = time.perf_counter()
        proposal = proposal_from_instance(inst, S)
        res = register(scene, lib, proposal)
        L = lib.to_world.detach().cpu().double().numpy()
        O = S @ res.transform.inverse().matrix() @ np.linalg.inv(L)
        specs.append(SubstitutedInstance(len(specs) + 1, lib, lib, O, proposal, inst.id))
        records.append({"instance": inst.id, "object": inst.library, "confidence": res.confidence,
                        "accepted": res.accepted, "seconds": time.perf_counter() - t0,
                        "max_abs_error_vs_truth": float(np.abs(O - inst.object_to_world).max())})
    return build_composite(scene, specs, composite or StageCompositeConfig(mode="substitute")), records


def _render_both(field: Field, camera: Camera, config: RenderBenchConfig, grid: DistanceGrid | None,
                 renderer: str):
    t0 = time.perf_counter()
    if renderer == "sphere":
        out = render(field, camera, config.sphere, grid=grid)
    elif renderer == "baked":
        out = render(field, camera, baked_tracing(config.sphere))
    elif renderer == "sphere-matched":
        coarse = dataclasses.replace(config.sphere, footprint_fraction=config.matched_footprint_fraction)
        out = render(field, camera, coarse, grid=grid)
    else:
        out = render_volume(field, camera, config.volume)
    return out, time.perf_counter() - t0


def speed_rows(cache: Cache, library: dict[str, Field], config: RenderBenchConfig, device: str,
               progress: bool, renderers: Sequence[str] = ("sphere", "baked", "sphere-matched", "volume"),
               ) -> tuple[list[dict], list[np.ndarray], list[dict]]:
    """Sphere tracer (of the neural fields, and of their baked grids) and volume renderer on the
    composite full-coverage room.

    The ``baked`` row bakes the composite for the views rendered (:func:`bake_for_views`,
    its time and grid nodes in ``bake_seconds`` and ``bake_nodes``), then sphere-traces it;
    its ``psnr_vs_neural`` compares each image with the ``sphere`` row's (which must come
    first)."""
    capture = cache.room_capture(ROOM, RoomCaptureConfig(coverage="full"))
    scene = load_field(cache.scene_field(ROOM, "full", device), device=device)
    neural, records = substituted_composite(scene, library, capture.instances, progress)
    room = make_room(ROOM, seed=RoomCaptureConfig().seed)
    test = capture.test_indices()
    picks = [test[i] for i in np.linspace(0, len(test) - 1, config.speed_views).round().astype(int)]
    cams = [Camera(capture.frames[i].intrinsics, capture.width, capture.height, capture.camtoworld_metres(i))
            for i in picks]
    rows, images = [], []
    neural_rgb: list[np.ndarray] = []
    with reference_renderer(room, capture.width, capture.height) as ref:
        for renderer in renderers:
            extra: dict = {}
            field = neural
            if renderer == "baked":
                baked = bake_for_views(neural, cams, config.bake, progress=progress)
                field = baked.field
                extra = {"bake_seconds": baked.seconds, "bake_nodes": baked.nodes}
            grid = None if renderer == "baked" else DistanceGrid.build(
                field, resolution=config.sphere.grid_resolution, lipschitz=config.sphere.grid_lipschitz)
            evals, secs, psnrs, vs_neural = [], [], [], []
            for k, cam in enumerate(tqdm(cams, desc=f"render {renderer}", disable=not progress)):
                gt = rgb_to_uint8(ref.render(cam.camera_to_world, cam.K).rgb)
                out, dt = _render_both(field, cam, config, grid, renderer)
                rgb = out.rgb.detach().cpu().numpy()
                evals.append(float(out.evals_per_pixel.double().mean()))
                secs.append(dt)
                psnrs.append(psnr(rgb, gt / 255.0))
                if renderer == "sphere":
                    neural_rgb.append(rgb)
                elif renderer == "baked":
                    vs_neural.append(psnr(rgb, neural_rgb[k]))
                if k == 0:
                    images.append((rgb * 255).round().astype(np.uint8))
                    if renderer == "sphere":
                        images.insert(0, gt)
            row = {"scene": f"{ROOM} (composite)", "renderer": renderer, "width": capture.width,
                   "height": capture.height, "views": len(cams),
                   "evals_per_pixel": float(np.mean(evals)), "seconds_per_frame": float(np.mean(secs)),
                   "psnr_vs_reference": float(np.mean(psnrs)), **extra}
            if vs_neural:
                row["psnr_vs_neural"] = float(np.mean(vs_neural))
                row["psnr_vs_neural_min"] = float(np.min(vs_neural))
            rows.append(row)
    return rows, images, records


def completion(cache: Cache, library: dict[str, Field], config: RenderBenchConfig, device: str,
               progress: bool) -> tuple[dict, list[np.ndarray]]:
    """Object completion on the low-coverage room: before / after on unseen views."""
    low = RoomCaptureConfig(coverage="low")
    capture = cache.room_capture(ROOM, low)
    scene = load_field(cache.scene_field(ROOM, "low", device), device=device)
    field, records = substituted_composite(scene, library, capture.instances, progress,
                                           config.completion_removal)
    room = make_room(ROOM, seed=low.seed)
    meshes = room.instance_meshes()
    grid_before = DistanceGrid.build(scene, resolution=config.sphere.grid_resolution,
                                     lipschitz=config.sphere.grid_lipschitz)
    grid_after = DistanceGrid.build(field, resolution=config.sphere.grid_resolution,
                                    lipschitz=config.sphere.grid_lipschitz)
    per_object, images = [], []
    with reference_renderer(room) as ref:
        for k, inst in enumerate(room.instances):
            if inst.library not in library:
                continue
            centre = meshes[k].bounds.mean(axis=0)
            stats = {"before": [], "after": []}
            cams = unseen_cameras(room, centre, config.completion_views, config.completion_distance,
                                  config.completion_height, free=scene)
            for j, cam in enumerate(tqdm(cams, desc=f"complete {inst.id}",
                                         disable=not progress)):
                gt = ref.render(cam.camera_to_world, cam.K)
                gt_rgb, gt_depth = rgb_to_uint8(gt.rgb), gt.depth.numpy()
                region = gt.instance_id.numpy() == k
                if not region.any():
                    continue
                row = []
                for tag, f, grid in (("before", scene, grid_before), ("after", field, grid_after)):
                    out = render(f, cam, config.sphere, grid=grid)
                    rgb = out.rgb.detach().cpu().numpy()
                    depth = out.depth.detach().cpu().numpy()
                    stats[tag].append((psnr(rgb[region], gt_rgb[region] / 255.0),
                                       float(np.abs(depth[region] - gt_depth[region]).mean())))
                    row.append((rgb * 255).round().astype(np.uint8))
                if j == 0:
                    images.append(np.concatenate([*row, gt_rgb], axis=1))
            per_object.append({
                "instance": inst.id, "object": inst.library, "views": len(stats["after"]),
                "psnr_before": float(np.mean([s[0] for s in stats["before"]])),
                "psnr_after": float(np.mean([s[0] for s in stats["after"]])),
                "depth_mae_before": float(np.mean([s[1] for s in stats["before"]])),
                "depth_mae_after": float(np.mean([s[1] for s in stats["after"]])),
            })
    summary = {k: float(np.mean([o[k] for o in per_object]))
               for k in ("psnr_before", "psnr_after", "depth_mae_before", "depth_mae_after")}
    return {"scene": f"{ROOM} (low coverage)", "views_per_object": config.completion_views,
            **summary, "objects": per_object, "registrations": records}, images


QUICK_VIEWS = 2
"""Views of the speed rows in the quick mode."""
QUICK_RENDERERS = ("sphere", "baked", "volume")
"""Speed rows of the quick mode (the matched sphere tracer is left out)."""


def run_render_benchmark(cache: Cache, config: RenderBenchConfig = RenderBenchConfig(),
                         device: str = "cpu", quick: bool = False) -> tuple[dict, dict[str, list[np.ndarray]]]:
    """Speed rows, the completion and the replacement records (JSON-ready), and the images to show.

    ``quick``: the speed rows alone (:data:`QUICK_RENDERERS` on :data:`QUICK_VIEWS` views), with no
    completion or replacement, so that no low-coverage field is trained.
    """
    capture = cache.room_capture(ROOM, RoomCaptureConfig(coverage="full"))
    names = sorted({inst.library for inst in capture.instances})
    library = {n: load_field(cache.object_field(n, "rgbd", device), device=device) for n in names}
    progress = cache.progress
    if quick:
        config = dataclasses.replace(config, speed_views=QUICK_VIEWS)
        rows, speed_images, records = speed_rows(cache, library, config, device, progress, QUICK_RENDERERS)
        return {"rows": rows, "registrations": records}, {"speed": speed_images}
    rows, speed_images, records = speed_rows(cache, library, config, device, progress)
    comp, comp_images = completion(cache, library, config, device, progress)
    repl, repl_images = replacement(cache, library, config, device, progress)
    return ({"rows": rows, "registrations": records, "completion": comp, "replacement": repl},
            {"speed": speed_images, "completion": comp_images, "replacement": repl_images})


def _surface_points(field: Field, to_scene: np.ndarray, resolution: int = 64) -> np.ndarray:
    """(n, 3) vertices of the field's marching-cubes surface in scene metres."""
    mesh = extract_mesh(field, resolution=resolution, with_color=False)
    L = field.to_world.detach().cpu().double().numpy()
    M = to_scene @ L
    return np.asarray(mesh.vertices, np.float64) @ M[:3, :3].T + M[:3, 3]


def _sdf_metres(field: Field, points: np.ndarray, field_to_scene: np.ndarray) -> np.ndarray:
    """SDF of ``field`` placed by ``field_to_scene`` (field frame -> scene metres) at scene points."""
    inv = np.linalg.inv(field_to_scene)
    x = points @ inv[:3, :3].T + inv[:3, 3]
    s = float(np.cbrt(abs(np.linalg.det(field_to_scene[:3, :3]))))
    with torch.no_grad():
        d = field.sdf(torch.as_tensor(x, dtype=torch.float32, device=field.device))
    return d.double().cpu().numpy() * s


def replacement(cache: Cache, library: dict[str, Field], config: RenderBenchConfig, device: str,
                progress: bool, seeds: Sequence[int] = (0, 1, 2)) -> tuple[dict, list[np.ndarray]]:
    """Random same-class replacement on the full-coverage room: floor contact, heading,
    intersections and remnants of the removed objects, per seed.

    - floor: the new object's lowest surface point (its field's marching-cubes surface) above
      the floor (z = 0), as a fraction of its height;
    - heading: angle between the new object's forward axis and the removed instance's true one;
    - intersection: deepest penetration (metres) of a new object's surface into another new
      object or into what is left of the scene;
    - remnant: pixels of the removed objects' true masks (pyrender) that still show the scene
      field at a depth more than ``remnant_tolerance`` in front of the empty room's depth.
    """
    capture = cache.room_capture(ROOM, RoomCaptureConfig(coverage="full"))
    scene = load_field(cache.scene_field(ROOM, "full", device), device=device)
    S = scene.to_world.detach().cpu().double().numpy()
    room = make_room(ROOM, seed=RoomCaptureConfig().seed)
    meshes = room.instance_meshes()
    registered = []  # (instance, its true index in the room, registered object -> scene)
    for inst in capture.instances:
        lib = library[inst.library]
        res = register(scene, lib, proposal_from_instance(inst, S))
        L = lib.to_world.detach().cpu().double().numpy()
        k = next(i for i, r in enumerate(room.instances) if r.id == inst.id)
        registered.append((inst, k, S @ res.transform.inverse().matrix() @ np.linalg.inv(L)))
    classes: dict[str, list[str]] = {}
    for name, f in sorted(library.items()):
        classes.setdefault(f.label, []).append(name)
    cams = []
    for inst, k, _ in registered:
        cams += unseen_cameras(room, meshes[k].bounds.mean(axis=0), 2, config.completion_distance,
                               config.completion_height, free=scene)
    with reference_renderer(room) as ref:  # one GL context at a time
        gts = [ref.render(c.camera_to_world, c.K) for c in cams]
    with RGBDRenderer([shaded_copy(room.mesh)], WIDTH, HEIGHT) as empty:
        empties = [empty.render(c.camera_to_world, c.K).depth.numpy() for c in cams]
    removed_masks = [g.instance_id.numpy() >= 0 for g in gts]
    per_seed, images = [], []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        specs, placed = [], []
        for j, (inst, k, O) in enumerate(registered):
            others = [n for n in classes[library[inst.library].label] if n != inst.library] or [inst.library]
            new = others[int(rng.integers(len(others)))]
            specs.append(SubstitutedInstance(j + 1, library[new], library[inst.library], O, None, inst.id))
            placed.append((new, O))
        field = build_composite(scene, specs, StageCompositeConfig(mode="substitute"))
        surfaces = [_surface_points(library[n], O) for n, O in placed]
        floor_rel, heading, penetration = [], [], 0.0
        for j, ((inst, k, O), (new, _), pts) in enumerate(zip(registered, placed, surfaces)):
            height = float(pts[:, 2].max() - pts[:, 2].min())
            floor_rel.append(abs(float(pts[:, 2].min())) / height)
            fwd, true_fwd = O[:3, 0], inst.object_to_world[:3, 0]
            heading.append(abs(math.atan2(fwd[1], fwd[0]) - math.atan2(true_fwd[1], true_fwd[0])))
            for i, (other, O2) in enumerate(placed):
                if i != j:
                    L2 = library[other].to_world.detach().cpu().double().numpy()
                    penetration = max(penetration, float(-_sdf_metres(library[other], pts, O2 @ L2).min()))
            with torch.no_grad():
                rest = field.scene_masked(world_to_field(field, pts)).sdf  # the composite's frame is the scene's
            above = pts[:, 2] > 0.02  # the base touches the floor by design
            if above.any():
                penetration = max(penetration, float(-(rest.detach().double().cpu().numpy()[above]).min()
                                                     * scene.world_scale))
        grid = DistanceGrid.build(field, resolution=config.sphere.grid_resolution,
                                  lipschitz=config.sphere.grid_lipschitz)
        remnant, total = 0, 0
        for c, mask, back in zip(cams, removed_masks, empties):
            out = render(field, c, config.sphere, grid=grid)
            ids = out.instance_id.cpu().numpy()
            depth = out.depth.cpu().numpy()
            shows_scene = mask & (ids == 0)
            remnant += int((shows_scene & (depth < back - config.remnant_tolerance)).sum())
            total += int(mask.sum())
            if len(images) < 4 and seed == seeds[0]:
                images.append((out.rgb.cpu().numpy() * 255).round().astype(np.uint8))
        per_seed.append({"seed": seed, "selections": {r[0].id: p[0] for r, p in zip(registered, placed)},
                         "floor_gap_rel_height_max": float(max(floor_rel)),
                         "heading_error_rad_max": float(max(heading)),
                         "penetration_m_max": penetration,
                         "remnant_pixels": remnant, "removed_object_pixels": total})
    return {"scene": f"{ROOM} (full coverage)", "views": len(cams), "seeds": per_seed}, images
