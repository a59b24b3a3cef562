"""Registration benchmark: the paper's Table I (11 scene/object pairs x methods) and Table II
(single uninformative view versus multi-view sampling), a scale sweep, the same 11 pairs on
the low-coverage rooms and with mesh-distilled libraries, and wrong-object pairs.

Fields come from the cache (trained once, see ``regnf bench fields``); proposals are the
instances' ground-truth boxes (the paper's assumption); every method goes through the same
sampling and the same metrics.

Rows: one per registration, with the scene, the library ``object`` registered, the ``method``,
``views``, the error metrics of :func:`regnf.registration.metrics.registration_errors`, ``seconds``
(and ``seconds_sampling``, ``seconds_initialisation``, ``seconds_refinement``: its stages),
``confidence``, ``accepted``, the confidence's factors (``inlier_fraction``, both directions,
and its ``inlier_fraction_scene`` and ``inlier_fraction_library`` parts; ``containment``), the
refinement's ``iterations``, and ``coverage`` (``full`` or ``low``: which capture the scene
field was trained on), ``library_source`` (``rgbd`` or ``mesh``), ``wrong_pair`` (the box holds
another object), ``box_object`` (the library name of the object the box really holds) and, for
a wrong pair, ``difference_observed`` (how much of the surface where the two objects differ the
scene's views observed, see :mod:`regnf.benchmarks.observed_difference`; null for a right pair). A
wrong pair has no true pose: its error metrics are null.

Wrong pairs (``wrong_pairs=True``): on every room, coverage and library source, every library
object of one class into every box of the other class (chairs into tables' boxes and the
reverse), and every chair into every other chair's box. An identification that works rejects
every cross-class pair, and gives each wrong chair a lower confidence than the right chair for
its box (or rejects it), as far as the scene observed what tells the two apart: a wrong chair
that differs from the right one only where no view looked (``difference_observed`` near 0)
fits the observed evidence as well as the right one, and the report counts it apart.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from regnf.benchmarks.observed_difference import observed_difference
from regnf.core.executors import ExecutorConfig, run_tasks
from regnf.fields.analytic import Transformed
from regnf.fields.field import Field
from regnf.fields.similarity import similarity_matrix
from regnf.io.checkpoint import load_field
from regnf.registration.methods import METHODS as REGISTRATION_METHODS
from regnf.registration.methods import PairHints
from regnf.registration.metrics import RegistrationErrors
from regnf.registration.pipeline import (
    RegistrationConfig,
)
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.ground_truth import (
    evaluate,
    find_instance,
    pair_truth,
    proposal_from_instance,
)
from regnf.synthetic.library import LIBRARY_NAMES, make_library_object
from regnf.synthetic.rooms import ROOM_CONTENTS

TABLE_I_PAIRS: tuple[tuple[str, str], ...] = (
    ("ac-room", "c"), ("ac-room", "dc"), ("ac-room", "fc"), ("ac-room", "fc-nop"), ("ac-room", "mc"),
    ("atbl-room", "et"), ("atbl-room", "t"), ("atbl-room", "wt"),
    ("mix-room", "dc"), ("mix-room", "fc"), ("mix-room", "t"),
)
"""The paper's Table I: room, library object."""

QUICK_PAIRS = (("ac-room", "dc"), ("atbl-room", "t"), ("mix-room", "fc"))

COVERAGES = ("full", "low")
"""Room captures: the full trajectory, or the short low-coverage one (objects seen from a side)."""
LIBRARY_SOURCES = ("rgbd", "mesh")
"""Library fields trained from RGB-D captures of the objects, or distilled from their meshes."""
REFERENCE = ("full", "rgbd")
"""The (coverage, library source) of Table I with every method, Table II and the scale sweep."""

METHODS = tuple(REGISTRATION_METHODS)
"""Every method the benchmark runs (:data:`regnf.registration.methods.METHODS`)."""

# The paper's published Table I (Delta t, Delta R, Delta s) for Reg-NF, for the side-by-side table.
PAPER_REGNF = {
    ("ac-room", "c"): (0.04, 0.048, 0.019), ("ac-room", "dc"): (0.035, 0.039, 0.007),
    ("ac-room", "fc"): (0.018, 0.031, 0.007), ("ac-room", "fc-nop"): (0.014, 0.020, 0.060),
    ("ac-room", "mc"): (0.007, 0.009, 0.003), ("atbl-room", "et"): (0.398, 2.6, 0.019),
    ("atbl-room", "t"): (0.044, 0.053, 0.004), ("atbl-room", "wt"): (0.022, 0.025, 0.006),
    ("mix-room", "dc"): (0.292, 0.641, 0.021), ("mix-room", "fc"): (0.029, 0.030, 0.009),
    ("mix-room", "t"): (0.009, 0.012, 0.005),
}


def scaled_library(field: Field, factor: float) -> Field:
    """The same object in a frame ``factor`` times larger (metres unchanged via ``to_world``)."""
    S = np.asarray(similarity_matrix(np.eye(3), np.zeros(3), factor))
    L = field.to_world.detach().cpu().double().numpy()
    wrapped = Transformed(field, S)
    wrapped.to_world = torch.as_tensor(L @ np.linalg.inv(S), dtype=torch.float64, device=field.device)
    wrapped.info = dataclasses.replace(field.info)
    return wrapped


METRIC_KEYS = tuple(RegistrationErrors._fields)
"""Error columns of a row (null for a wrong pair)."""


def run_pair(scene_name: str, obj: str, scene: Field, library: Field, capture, methods, single_view: bool,
             cfg: RegistrationConfig, seed: int = 0, box_object: str | None = None,
             coverage: str = "full", library_source: str = "rgbd") -> list[dict]:
    """Rows of library object ``obj`` registered into the box of ``box_object`` (default: its own)."""
    box_object = box_object or obj
    wrong = box_object != obj
    inst = find_instance(capture.instances, box_object)
    if wrong:  # no true pose: only the box is used
        S = scene.to_world.detach().cpu().double().numpy()
        proposal, truth, surface_lib, diag = proposal_from_instance(inst, S), None, None, float("nan")
        difference = observed_difference(scene, inst.object_to_world, make_library_object(obj).mesh,
                                         make_library_object(box_object).mesh)
    else:
        truth, proposal, surface_lib, diag = pair_truth(inst, scene, library, seed)
        difference = None
    if single_view:
        cfg = dataclasses.replace(cfg, scene_sampling=dataclasses.replace(cfg.scene_sampling, views="single"))
    hints = PairHints(truth, surface_lib, seed)
    rows = []
    for m in methods:
        t = time.perf_counter()
        res = REGISTRATION_METHODS[m](scene, library, proposal, cfg, hints)
        seconds = time.perf_counter() - t
        errors = (dict.fromkeys(METRIC_KEYS) if wrong
                  else evaluate(res, truth, scene, library, surface_lib, diag))
        rows.append({
            "scene": scene_name, "object": obj, "method": m,
            "views": "single" if single_view else "multi",
            **errors,
            "seconds": seconds, "confidence": res.confidence, "accepted": res.accepted,
            # The confidence's factors (null where a method does not report one).
            **{k: (float(res.losses[k]) if k in res.losses else None)
               for k in ("inlier_fraction", "inlier_fraction_scene", "inlier_fraction_library", "containment",
                         "seen_free")},
            "iterations": float(res.losses["iterations"]) if "iterations" in res.losses else None,
            # Where the time goes (null for a stage the method does not have).
            **{f"seconds_{stage}": (float(res.timings[stage]) if stage in res.timings else None)
               for stage in ("sampling", "initialisation", "refinement")},
            "coverage": coverage, "library_source": library_source, "wrong_pair": wrong,
            "box_object": box_object, "difference_observed": difference,
            "_result": res, "_truth": truth,
        })
    return rows


class PairTask(NamedTuple):
    """One scene/object pair of the benchmark, as sent to a worker."""

    cache_root: str
    """Cache directory holding the fields (made beforehand by the driver)."""
    scene: str
    """Room name."""
    obj: str
    """Library object name."""
    methods: tuple[str, ...]
    """Methods to run."""
    single_view: bool
    """Table II: sample the scene from one uninformative view."""
    library_factor: float = 1.0
    """Scale sweep: the library field in a frame this many times larger (1: as trained)."""
    device: str = "cpu"
    """Torch device."""
    coverage: str = "full"
    """Capture of the scene field: ``full`` or ``low``."""
    library_source: str = "rgbd"
    """Library field: trained from RGB-D (``rgbd``) or distilled from the mesh (``mesh``)."""
    box_object: str | None = None
    """The object whose box is the proposal (None: ``obj`` itself; another one: a wrong pair)."""
    cache_size: str = "full"
    """The cache's ``size`` (``Cache.size``: ``tiny`` in the tests)."""


def wrong_pairs(scene: str) -> list[tuple[str, str]]:
    """(library object, box object) wrong pairs of a room: every object of the other class into
    each box, and every other chair into each chair's box."""
    labels = {name: make_library_object(name).label for name in LIBRARY_NAMES}
    out = []
    for box in ROOM_CONTENTS[scene]:
        for obj in LIBRARY_NAMES:
            if obj == box:
                continue
            if labels[obj] != labels[box] or labels[box] == "chair":
                out.append((obj, box))
    return out


def benchmark_tasks(cache: Cache, quick: bool = False, single_view: bool = True,
                    methods=METHODS, device: str = "cpu", coverages: tuple[str, ...] = ("full",),
                    library_sources: tuple[str, ...] = ("rgbd",), with_wrong_pairs: bool = False) -> list[PairTask]:
    """One task per pair: Table I (every method), Table II (single view, ``regnf``) and the scale
    sweep on the reference (full coverage, RGB-D library); the 11 pairs with ``regnf`` on every
    other coverage and library source asked for; and the wrong pairs of each."""
    pairs = QUICK_PAIRS if quick else TABLE_I_PAIRS
    root = str(cache.root)
    tasks: list[PairTask] = []
    for coverage in coverages:
        for source in library_sources:
            reference = (coverage, source) == REFERENCE
            run = tuple(methods) if reference else ("regnf",)
            tasks += [PairTask(root, scene, obj, run, False, 1.0, device, coverage, source) for scene, obj in pairs]
            if reference and single_view and not quick:
                first: dict[str, str] = {}
                for scene, obj in pairs:
                    first.setdefault(obj, scene)
                tasks += [PairTask(root, scene, obj, ("regnf",), True, 1.0, device, coverage, source)
                          for obj, scene in first.items()]
            if reference and not quick:
                tasks += [PairTask(root, "ac-room", "dc", ("regnf",), False, f, device, coverage, source)
                          for f in (0.25, 4.0)]
            if with_wrong_pairs:
                scenes = sorted({scene for scene, _ in pairs})
                tasks += [PairTask(root, scene, obj, ("regnf",), False, 1.0, device, coverage, source, box)
                          for scene in scenes for obj, box in wrong_pairs(scene)]
    return [t._replace(cache_size=cache.size) for t in tasks]


def prepare_fields(cache: Cache, tasks: list[PairTask]) -> None:
    """Make every field and capture the tasks need (here, once), so that workers only read them."""
    for scene, coverage in sorted({(t.scene, t.coverage) for t in tasks}):
        cache.room_capture(scene, RoomCaptureConfig(coverage=coverage))
        cache.scene_field(scene, coverage, tasks[0].device)
    for obj, source in sorted({(t.obj, t.library_source) for t in tasks}):
        cache.object_field(obj, source, tasks[0].device)


# Per worker process: scene fields and captures already loaded (a worker runs many pairs).
_LOADED: dict[tuple[str, str, str, str, str], tuple[Field, object]] = {}


def run_pair_task(task: PairTask) -> list[dict]:
    """The rows of one pair (runs in a worker; fields must already be in the cache)."""
    cache = Cache(Path(task.cache_root), progress=False, size=task.cache_size)
    key = (task.cache_root, task.cache_size, task.scene, task.coverage, task.device)
    if key not in _LOADED:
        capture = cache.room_capture(task.scene, RoomCaptureConfig(coverage=task.coverage))
        scene = load_field(cache.scene_field(task.scene, task.coverage, task.device), device=task.device)
        _LOADED[key] = (scene, capture)
    scene, capture = _LOADED[key]
    library = load_field(cache.object_field(task.obj, task.library_source, task.device), device=task.device)
    if task.library_factor != 1.0:
        library = scaled_library(library, task.library_factor)
    rows = run_pair(task.scene, task.obj, scene, library, capture, task.methods, task.single_view,
                    RegistrationConfig(), box_object=task.box_object, coverage=task.coverage,
                    library_source=task.library_source)
    if task.library_factor != 1.0:
        for r in rows:
            r["method"] = f"regnf (library x{task.library_factor:g})"
    return rows


def run_registration_benchmark(cache: Cache, quick: bool = False, single_view: bool = True,
                               methods=METHODS, device: str = "cpu",
                               executor: ExecutorConfig | None = None,
                               coverages: tuple[str, ...] = ("full",),
                               library_sources: tuple[str, ...] = ("rgbd",),
                               with_wrong_pairs: bool = False) -> list[dict]:
    """All rows of :func:`benchmark_tasks` (see the module for what each row holds).

    The pairs run as tasks on ``executor`` (default: a local pool of one worker using every
    core, so each pair's time is that of a whole machine); rows come back in task order
    whatever the order of completion. A pair that fails stops the benchmark with its error.
    """
    executor = executor or ExecutorConfig(workers=1, threads_per_task=max(1, torch.get_num_threads()))
    tasks = benchmark_tasks(cache, quick, single_view, methods, device, coverages, library_sources,
                            with_wrong_pairs)
    prepare_fields(cache, tasks)
    results: dict[int, list[dict]] = {}
    bar = tqdm(total=len(tasks), desc=f"bench registration ({executor.kind})", disable=not cache.progress)
    for outcome in run_tasks(run_pair_task, tasks, executor):
        if outcome.error is not None:
            t = tasks[outcome.index]
            raise RuntimeError(f"registration benchmark, pair {t.scene}/{t.obj}: {outcome.error}")
        results[outcome.index] = outcome.value
        bar.update(1)
    bar.close()
    return [row for i in range(len(tasks)) for row in results[i]]
