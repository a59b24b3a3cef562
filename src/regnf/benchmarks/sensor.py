"""``regnf bench sensor``: the rooms' fields, registrations and discoveries from noisy captures.

Per noise level (:data:`regnf.synthetic.sensor_noise.NOISE_LEVELS`: ``ideal``, ``sensor``,
``slam``, ``harsh``), coverage and room: the room's capture at that level (made once in the
cache with seed ``noise_seed``; ``ideal`` is the very capture, and field, the other benchmarks
use) and its scene field trained with the room preset (the cache), then

- the field's surface error at the true instance meshes (mean and p95 of |SDF| over each
  instance's diagonal, :func:`regnf.render.evaluation.surface_error`, as the fields
  benchmark measures a room);
- the room's Table I pairs registered from their true boxes with the mesh-distilled library
  (:func:`regnf.benchmarks.registration.run_pair`: the registration benchmark's rows and
  errors), and its wrong pairs (:func:`regnf.benchmarks.registration.wrong_pairs`);
- per object, the median position and rotation error of the training cameras that see it
  (:func:`regnf.benchmarks.camera_error.object_camera_errors`), and the bars widened by them
  (:func:`widened_bars`);
- discovery with the whole mesh library and no boxes (:func:`regnf.registration.discovery.discover`),
  scored as the discovery benchmark scores it (:func:`regnf.benchmarks.discover.score_room`).

The result (JSON)::

    {"pairs": [...],    # one per registration: run_pair's row, plus level, noise_seed, cameras,
                        # camera_position_cm, camera_rotation_deg, bars_widened, within_bars,
                        # within_widened_bars (the last five null for a wrong pair)
     "rooms": [...],    # one per level, coverage and room: surface error, train_seconds,
                        # discovery (score_room's row, or null), seconds
     "summary": [...]}  # one per level and coverage: counts, checks, verdict (sensor_report)
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from tqdm import tqdm

from regnf.benchmarks.camera_error import object_camera_errors
from regnf.benchmarks.discover import LIBRARY, score_room
from regnf.benchmarks.registration import TABLE_I_PAIRS, run_pair, wrong_pairs
from regnf.benchmarks.sensor_report import summarise
from regnf.core.preflight import PreflightError
from regnf.fields.field import Field
from regnf.io.checkpoint import load_field
from regnf.registration.discovery import FieldFiles, discover
from regnf.registration.metrics import BARS, within_bars
from regnf.registration.pipeline import RegistrationConfig
from regnf.render.evaluation import surface_error
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.ground_truth import find_instance
from regnf.synthetic.library import instance_mesh, make_library_object
from regnf.synthetic.sensor_noise import NOISE_LEVELS

LEVELS = tuple(NOISE_LEVELS)
"""The noise levels, in order of severity."""
COVERAGES = ("low", "full")
"""Room captures: the short low-coverage arc and the full trajectory."""
ROOMS = ("ac-room", "atbl-room", "mix-room")
"""The rooms of Table I."""
LIBRARY_SOURCE = "mesh"
"""Library fields distilled from the meshes: the same library for every level."""


def widened_bars(position_cm: float | None, rotation_deg: float | None, diagonal_m: float) -> dict[str, float]:
    """The bars of one object widened by the error of the cameras that see it.

    Translation: the bar plus the cameras' median position error over the object's diagonal;
    rotation: the bar plus their median rotation error; scale: the bar. An object no camera
    sees (None) keeps the plain bars.

    Parameters
    ----------
    position_cm, rotation_deg : float or None
        Median position (cm) and rotation (degrees) error of the cameras that see the object.
    diagonal_m : float
        The object's bounding-box diagonal, metres.

    Returns
    -------
    dict
        The keys of :data:`regnf.registration.metrics.BARS`, in their units.
    """
    return {"rot_geodesic_sym_rad": BARS["rot_geodesic_sym_rad"] + math.radians(rotation_deg or 0.0),
            "trans_rel_diag_sym": BARS["trans_rel_diag_sym"] + (position_cm or 0.0) / 100.0 / diagonal_m,
            "scale_rel": BARS["scale_rel"]}


def object_diagonal(name: str) -> float:
    """The bounding-box diagonal of library object ``name``, metres (the errors' denominator)."""
    bounds = make_library_object(name).mesh.bounds
    return float(np.linalg.norm(bounds[1] - bounds[0]))


def check_selection(levels: tuple[str, ...], coverages: tuple[str, ...], rooms: tuple[str, ...],
                    objects: tuple[str, ...]) -> None:
    """Refuse, before any work, a selection that names nothing the benchmark has.

    Raises
    ------
    PreflightError
        An unknown level, coverage or room, an object of no selected room's pairs, or an empty selection.
    """
    for option, given, known in (("--levels", levels, LEVELS), ("--coverages", coverages, COVERAGES),
                                 ("--rooms", rooms, ROOMS)):
        unknown = [g for g in given if g not in known]
        if unknown or not given:
            raise PreflightError(f"{option} {' '.join(unknown) or '(nothing)'}: choose from {' '.join(known)}")
    paired = sorted({o for s, o in TABLE_I_PAIRS if s in rooms})
    stray = [o for o in objects if o not in paired]
    if stray:
        raise PreflightError(f"--objects {' '.join(stray)}: no pair of the rooms {' '.join(rooms)} has it; "
                             f"choose from {' '.join(paired)}")


def room_pairs(room: str, objects: tuple[str, ...], with_wrong_pairs: bool) -> list[tuple[str, str]]:
    """(library object, box object) registrations of a room: its Table I pairs among ``objects``
    (empty: all), then its wrong pairs into those boxes."""
    right = [o for s, o in TABLE_I_PAIRS if s == room and (not objects or o in objects)]
    wrong = [(o, box) for o, box in wrong_pairs(room) if box in right] if with_wrong_pairs else []
    return [(o, o) for o in right] + wrong


def bar_columns(row: dict, camera: dict, diagonal_m: float) -> dict:
    """The columns a true-box row gets from the error of the cameras that see its object.

    Parameters
    ----------
    row : dict
        A right-object registration row (its error columns).
    camera : dict
        The object's entry of :func:`regnf.benchmarks.camera_error.object_camera_errors`.
    diagonal_m : float
        The object's bounding-box diagonal, metres.

    Returns
    -------
    dict
        ``cameras``, ``camera_position_cm``, ``camera_rotation_deg``, ``bars_widened``
        (:func:`widened_bars`), ``within_bars`` (the plain bars) and ``within_widened_bars``.
    """
    bars = widened_bars(camera["position_cm"], camera["rotation_deg"], diagonal_m)
    return {"cameras": camera["cameras"], "camera_position_cm": camera["position_cm"],
            "camera_rotation_deg": camera["rotation_deg"], "bars_widened": bars,
            "within_bars": within_bars(row), "within_widened_bars": within_bars(row, bars)}


def register_room(room: str, coverage: str, scene: Field, capture, library: dict[str, Field],
                  pairs: list[tuple[str, str]], level: str, seed: int, progress: bool) -> list[dict]:
    """Rows of ``pairs`` registered in one room field (see the module for the columns)."""
    cameras = object_camera_errors(capture)
    rows = []
    for obj, box in tqdm(pairs, desc=f"{level} {coverage} {room}", leave=False, disable=not progress):
        (row,) = run_pair(room, obj, scene, library[obj], capture, ("regnf",), False, RegistrationConfig(),
                          box_object=box, coverage=coverage, library_source=LIBRARY_SOURCE)
        row = {k: v for k, v in row.items() if not k.startswith("_")}
        row.update(level=level, noise_seed=seed, cameras=None, camera_position_cm=None, camera_rotation_deg=None,
                   bars_widened=None, within_bars=None, within_widened_bars=None)
        if obj == box:
            row.update(bar_columns(row, cameras[find_instance(capture.instances, obj).id], object_diagonal(obj)))
        rows.append(row)
    return rows


def run_sensor_benchmark(cache: Cache, levels: tuple[str, ...] = LEVELS, coverages: tuple[str, ...] = COVERAGES,
                         rooms: tuple[str, ...] = ROOMS, objects: tuple[str, ...] = (),
                         with_wrong_pairs: bool = True, with_discovery: bool = True, noise_seed: int = 0,
                         device: str = "cpu", on_room: Callable[[dict], None] | None = None,
                         pose_refine: str = "auto") -> dict:
    """Every row of the benchmark (see the module) and its summary per level and coverage.

    ``objects`` restricts the true-box pairs (and the wrong pairs into their boxes) to those
    library objects; empty: every pair of the rooms. ``pose_refine`` (auto, on, off) is how the
    noisy rooms' fields refine their poses. ``on_room`` is called with the result so
    far after each room (to write it as it grows).
    """
    check_selection(levels, coverages, rooms, objects)
    # A level, coverage or room named twice runs once.
    levels, coverages, rooms = (tuple(dict.fromkeys(x)) for x in (levels, coverages, rooms))
    jobs = [(lv, cov, room) for lv in levels for cov in coverages for room in rooms]
    plans = {room: room_pairs(room, objects, with_wrong_pairs) for room in rooms}
    needed = sorted(set(LIBRARY) if with_discovery else {o for p in plans.values() for o, _ in p})
    paths = {name: cache.object_field(name, LIBRARY_SOURCE, device) for name in needed}
    library = {name: load_field(p, device=device) for name, p in paths.items()}
    result: dict = {"pairs": [], "rooms": [], "summary": []}
    for level, coverage, room in tqdm(jobs, desc="bench sensor", disable=not cache.progress):
        t0 = time.perf_counter()
        # The noise seed means nothing at ideal: kept at 0 there, the capture and field are the
        # cached ones the other benchmarks use.
        seed = noise_seed if level != "ideal" else 0
        capture = cache.room_capture(room, RoomCaptureConfig(coverage=coverage, noise=level, noise_seed=seed))
        scene_path = cache.scene_field(room, coverage, device, noise=level, noise_seed=seed, pose_refine=pose_refine)
        scene = load_field(scene_path, device=device)
        surface = surface_error(scene, [instance_mesh(inst) for inst in capture.instances])
        t_reg = time.perf_counter()
        pairs = register_room(room, coverage, scene, capture, library, plans[room], level, seed, cache.progress)
        t_disc = time.perf_counter()
        found = None
        if with_discovery:
            outcome = discover(scene, library, files=FieldFiles(scene_path, paths))
            found = score_room(room, coverage, LIBRARY_SOURCE, outcome, scene, library, capture.instances)
        result["pairs"] += pairs
        result["rooms"].append({
            "level": level, "noise_seed": seed, "scene": room, "coverage": coverage,
            "surface_error_mean_rel": surface.mean_rel, "surface_error_p95_rel": surface.p95_rel,
            "train_seconds": float(scene.info.provenance.get("train_seconds", float("nan"))),
            "registration_seconds": t_disc - t_reg,
            "discovery_seconds": time.perf_counter() - t_disc if with_discovery else None,
            "discovery": found, "seconds": time.perf_counter() - t0, "checkpoint": str(scene_path)})
        result["summary"] = [summarise(result["pairs"], result["rooms"], lv, cov)
                             for lv in levels for cov in coverages
                             if any(r["level"] == lv and r["coverage"] == cov for r in result["rooms"])]
        if on_room is not None:
            on_room(result)
    return result
