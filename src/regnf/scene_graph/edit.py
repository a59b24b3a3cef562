"""Make and change stages: a new stage from fields, instances by hand or from registrations.

Each operation holds the lock of the stage's folder (:func:`regnf.scene_graph.locking.stage_lock`)
from before it reads the stage until after it has written it, so that two processes editing
one stage at once (two ``regnf register --stage`` runs) both get their change in, one after
the other. It reads the stage, changes the model, checks it and writes every file in one
transaction: on any error the stage on disk is left exactly as it was. Work that does not
depend on the stage (meshing a proxy, checking a registration result) is done before the
lock is taken, so that the lock is held briefly.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np
import trimesh

from . import layout as L
from .checks import check_registration, check_similarity, is_number
from .errors import StageError
from .fields import ProxyConfig, checkpoint_name, field_record
from .locking import stage_lock
from .model import ComposedScene, InstanceRecord, RegistrationProvenance
from .usd_read import read_stage
from .usd_write import write_stage

PRODUCER = "regnf scene_graph"
RESULT = "<registration result>"
"""Named as the file at fault when a registration result is checked without a stage."""
REQUIRED_KEYS = ("library_name", "object_to_scene_metres", "accepted", "confidence")
"""Keys a registration result must have to become an instance."""


def new_stage(
    stage_path: str | os.PathLike,
    scene_checkpoint: str | os.PathLike,
    library_checkpoints: Sequence[str | os.PathLike] = (),
    config: ProxyConfig | None = None,
    proxies: Mapping[str, trimesh.Trimesh] | None = None,
    provenance: dict | None = None,
    overwrite: bool = False,
) -> ComposedScene:
    """Write a new stage with a scene field and library objects, and no instances.

    Parameters
    ----------
    stage_path : str or PathLike
        The stage to create (.usda or .usdc); its assets are written beside it.
    scene_checkpoint : str or PathLike
        The scene field.
    library_checkpoints : sequence of str or PathLike
        Library object fields; their names and classes come from their headers.
    config : ProxyConfig, optional
        Proxy meshing.
    proxies : mapping, optional
        Proxy meshes (metres) to use instead of marching cubes, by field name ("scene" for
        the scene field).
    provenance : dict, optional
        Extra stage-level provenance (strings, numbers, bools, nested dicts).
    overwrite : bool
        Replace an existing stage.

    Returns
    -------
    ComposedScene
        As read back from the written stage.

    Raises
    ------
    StageError
        The stage exists (and not ``overwrite``), a bad checkpoint, a duplicate library name.
    regnf.core.file_lock.LockBusy
        Another process kept the folder locked for :data:`~regnf.scene_graph.locking.STAGE_LOCK_TIMEOUT_S`.
    """
    stage_path = Path(stage_path).absolute()
    if stage_path.exists() and not overwrite:  # before meshing proxies, which takes a while
        raise StageError(stage_path, "/", "the stage already exists (overwrite it explicitly)")
    proxies = dict(proxies or {})
    scene = field_record(scene_checkpoint, L.SCENE, config, proxies.get("scene"))
    library = {}
    for ckpt in library_checkpoints:
        name = checkpoint_name(ckpt, "/World/Library")
        rec = field_record(ckpt, f"</{L.prim_name(name)}>", config, proxies.get(name))
        if rec.name in library:
            raise StageError(ckpt, f"</{L.prim_name(rec.name)}>",
                             f"library name {rec.name!r} also used by {library[rec.name].checkpoint}")
        library[rec.name] = rec
    prov = {
        "producer": PRODUCER,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "sceneField": str(Path(scene_checkpoint)),
        **(provenance or {}),
    }
    with stage_lock(stage_path, create=True):
        if stage_path.exists() and not overwrite:  # again: another `stage new` may have won the race
            raise StageError(stage_path, "/", "the stage already exists (overwrite it explicitly)")
        write_stage(ComposedScene(scene, library, {}, prov), stage_path)
        return read_stage(stage_path)


def add_library_object(
    stage_path: str | os.PathLike,
    checkpoint: str | os.PathLike,
    config: ProxyConfig | None = None,
    proxy: trimesh.Trimesh | None = None,
    allow_outside: bool = False,
) -> str:
    """Add a library object (and its class's slot variant) to a stage; returns its name.

    Parameters
    ----------
    stage_path : str or PathLike
    checkpoint : str or PathLike
        The object's field (copied into the stage's ``fields/``).
    config : ProxyConfig, optional
    proxy : trimesh.Trimesh, optional
        Proxy mesh in metres instead of marching cubes.
    allow_outside : bool
        Read a stage whose asset paths leave its folder (see :func:`read_stage`); the stage
        written is self-contained.
    """
    stage_path = Path(stage_path).absolute()
    rec = field_record(checkpoint, "/World/Library", config, proxy)  # the slow part, before the lock
    with stage_lock(stage_path):
        scene = read_stage(stage_path, allow_outside=allow_outside)
        if rec.name in scene.library:
            raise StageError(stage_path, f"</{L.prim_name(rec.name)}>", f"library object {rec.name!r} exists already")
        scene.library[rec.name] = rec
        write_stage(scene, stage_path)
    return rec.name


def add_instance(
    stage_path: str | os.PathLike,
    library_name: str,
    object_to_scene: np.ndarray,
    registration: RegistrationProvenance | None = None,
    instance_id: str | None = None,
    allow_outside: bool = False,
) -> str:
    """Place a library object in the scene; returns the new instance's id.

    Parameters
    ----------
    stage_path : str or PathLike
    library_name : str
        A library object of the stage.
    object_to_scene : (4, 4) float
        Canonical object metres -> scene metres (a similarity: uniform positive scale).
    registration : RegistrationProvenance, optional
    instance_id : str, optional
        Prim name; ``<name>_<k>`` by default (the first free one when the edit runs).
    allow_outside : bool
        As for :func:`add_library_object`.
    """
    stage_path = Path(stage_path).absolute()
    with stage_lock(stage_path):
        scene = read_stage(stage_path, allow_outside=allow_outside)
        iid = instance_id or scene.new_instance_id(library_name)
        if iid in scene.instances:
            raise StageError(stage_path, L.instance_path(iid), "an instance with this id exists already")
        scene.edited_scene = None  # cut for the instances as they were
        scene.instances[iid] = InstanceRecord(iid, library_name, np.asarray(object_to_scene, dtype=np.float64),
                                              registration)
        write_stage(scene, stage_path)
    return iid


def set_instance(
    stage_path: str | os.PathLike,
    instance_id: str,
    object_to_scene: np.ndarray,
    registration: RegistrationProvenance | None = None,
    allow_outside: bool = False,
) -> None:
    """Move an existing instance: its transform and provenance are replaced, its library object
    and everything else in the stage kept (a pose corrected in ``regnf view``, for example).

    Parameters
    ----------
    stage_path : str or PathLike
    instance_id : str
        An instance of the stage (``StageError`` otherwise).
    object_to_scene : (4, 4) float
        Canonical object metres -> scene metres (a similarity).
    registration : RegistrationProvenance, optional
        How the new transform was found; None: placed by hand.
    allow_outside : bool
        As for :func:`add_library_object`.
    """
    stage_path = Path(stage_path).absolute()
    with stage_lock(stage_path):
        scene = read_stage(stage_path, allow_outside=allow_outside)
        old = scene.instances.get(instance_id)
        if old is None:
            raise StageError(stage_path, L.instance_path(instance_id),
                             f"no such instance (the stage has {sorted(scene.instances)})")
        scene.edited_scene = None  # cut for the instances as they were
        scene.instances[instance_id] = InstanceRecord(
            instance_id, old.library_name, np.asarray(object_to_scene, dtype=np.float64), registration)
        write_stage(scene, stage_path)


# -- registration results (JSON) ------------------------------------------------------------------
def _short(value: object) -> str:
    """``repr(value)``, cut to one short line for a message."""
    text = " ".join(repr(value).split())
    return text if len(text) <= 80 else text[:77] + "..."


def _numbers(value: object, shape: tuple[int, ...], key: str, fail: Callable[[str], NoReturn]) -> np.ndarray:
    """``value`` (nested lists of numbers) as a float64 array of ``shape``.

    Strings are refused although numpy would parse ``"1.0"``: a result that holds them was
    not written by ``regnf register``. Finiteness and the geometry are checked afterwards, by
    :mod:`regnf.scene_graph.checks`.
    """
    try:
        a = np.asarray(value, dtype=object)
    except ValueError:
        a = None
    if a is None or a.shape != shape:
        fail(f"'{key}' must be a {' x '.join(map(str, shape))} array of numbers, got {_short(value)}")
    if not all(is_number(x) for x in a.flat):
        fail(f"'{key}' must hold numbers only, got {_short(value)}")
    return a.astype(np.float64)


def _number_table(value: object, key: str, fail: Callable[[str], NoReturn],
                  keep_numbers_only: bool = False) -> dict[str, float]:
    """A ``{name: number}`` table (losses, timings, thresholds); None or missing is empty."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        fail(f"'{key}' must be an object of numbers, got {_short(value)}")
    if keep_numbers_only:  # thresholds may carry settings that are not numbers: not recorded
        return {k: float(v) for k, v in value.items() if is_number(v)}
    bad = [k for k, v in value.items() if not is_number(v)]
    if bad:
        fail(f"'{key}' entries {bad} are not numbers")
    return {k: float(v) for k, v in value.items()}


def parse_registration(
    result: Mapping,
    forced: bool = False,
    stage_path: str | os.PathLike = RESULT,
    prim: str = "/",
) -> tuple[str, np.ndarray, RegistrationProvenance]:
    """Check a registration result (``regnf register``'s JSON) completely and take it apart.

    Every field the stage records is checked for type, shape and finiteness, and the numbers
    then against :func:`regnf.scene_graph.checks.check_registration`, the rules the stage's reader
    applies, so that a result that passes here can be written, read back and rendered.

    Parameters
    ----------
    result : mapping
        ``library_name`` (str), ``object_to_scene_metres`` ((4, 4) similarity: uniform scale
        > 0, a proper rotation), ``accepted`` (a JSON boolean), ``confidence`` (a finite
        number); optionally ``method`` (str), ``transform_scene_to_library.matrix`` ((4, 4)
        similarity), ``losses`` / ``timings`` / ``thresholds`` (objects of numbers) and
        ``proposal_box`` (``center`` (3,), ``half_extents`` (3,) all > 0, ``rotation`` (3, 3)
        orthonormal with det +1), or null; ``discovery`` (an object of JSON data: how
        discovery found the instance), or null; ``warnings`` (a list of one-line strings), or null.
    forced : bool
        Recorded on the provenance (written although not accepted).
    stage_path : str or PathLike
        The stage it is for (named as the file in errors).
    prim : str
        The instance it would become (named in errors).

    Returns
    -------
    library_name : str
    object_to_scene : (4, 4) float64
    registration : RegistrationProvenance

    Raises
    ------
    StageError
        One line naming ``stage_path``, ``prim``, the key and what is wrong.
    """

    def fail(problem: str) -> NoReturn:
        raise StageError(stage_path, prim, f"registration result: {problem}")

    if not isinstance(result, Mapping):
        fail(f"must be a JSON object, got {type(result).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in result]
    if missing:
        raise StageError(stage_path, prim, f"the registration result lacks {missing}")
    name = result["library_name"]
    if not isinstance(name, str) or not name:
        fail(f"'library_name' must be a non-empty string, got {_short(name)}")
    M = _numbers(result["object_to_scene_metres"], (4, 4), "object_to_scene_metres", fail)
    try:
        check_similarity(M, "'object_to_scene_metres'")
    except ValueError as exc:
        fail(str(exc))
    T = result.get("transform_scene_to_library")
    if T is None:
        T_matrix = np.eye(4)
    elif isinstance(T, Mapping) and "matrix" in T:
        T_matrix = _numbers(T["matrix"], (4, 4), "transform_scene_to_library.matrix", fail)
    else:
        fail(f"'transform_scene_to_library' must be an object with a 'matrix', got {_short(T)}")
    box = result.get("proposal_box")
    center = half = rotation = None
    found = result.get("discovery")
    if found is not None and not isinstance(found, Mapping):
        fail(f"'discovery' must be null or an object, got {_short(found)}")
    if box is not None:
        if not isinstance(box, Mapping) or not {"center", "half_extents", "rotation"} <= set(box):
            fail(f"'proposal_box' must be null or an object with center, half_extents and rotation, got {_short(box)}")
        center = _numbers(box["center"], (3,), "proposal_box.center", fail)
        half = _numbers(box["half_extents"], (3,), "proposal_box.half_extents", fail)
        rotation = _numbers(box["rotation"], (3, 3), "proposal_box.rotation", fail)
    # As found: check_registration refuses a string for `accepted` (bool("false") is True), a
    # NaN or a bool for `confidence`, anything but a string for `method`.
    reg = RegistrationProvenance(
        method=result.get("method", "unknown"),
        confidence=result["confidence"],
        accepted=result["accepted"],
        library_name=name,
        scene_to_library=T_matrix,
        losses=_number_table(result.get("losses"), "losses", fail),
        timings=_number_table(result.get("timings"), "timings", fail),
        thresholds=_number_table(result.get("thresholds"), "thresholds", fail, keep_numbers_only=True),
        proposal_center=center,
        proposal_half_extents=half,
        proposal_rotation=rotation,
        forced=bool(forced),
        discovery=None if found is None else dict(found),
        warnings=[] if result.get("warnings") is None else result["warnings"],
    )
    try:
        check_registration(reg)
    except ValueError as exc:
        fail(str(exc))
    reg.confidence, reg.accepted = float(reg.confidence), bool(reg.accepted)
    return name, M, reg


def provenance_from_registration(result: Mapping, forced: bool = False) -> RegistrationProvenance:
    """The provenance kept on an instance, from ``regnf register``'s JSON (checked: see
    :func:`parse_registration`, whose ``StageError`` it raises)."""
    return parse_registration(result, forced)[2]


def add_instance_from_registration(
    stage_path: str | os.PathLike,
    result_json: Mapping,
    force: bool = False,
    instance_id: str | None = None,
    config: ProxyConfig | None = None,
    allow_outside: bool = False,
) -> str:
    """Write a registration (the JSON of ``regnf register``) as an instance; returns its id.

    The whole result is checked first (:func:`parse_registration`), before the stage is
    locked or read. The library object is added to the stage first if it is not there yet
    (from the result's ``library_field`` checkpoint). A registration that was not accepted
    (confidence below the threshold) is refused unless ``force``.

    Parameters
    ----------
    stage_path : str or PathLike
    result_json : mapping
        As :func:`parse_registration` describes.
    force : bool
        Write a result that was not accepted (flagged as forced).
    instance_id : str, optional
        Prim name; ``<name>_<k>`` by default.
    config : ProxyConfig, optional
        Proxy meshing for a library object added from ``library_field``.
    allow_outside : bool
        As for :func:`add_library_object`.

    Raises
    ------
    StageError
        Not accepted (and not forced), a malformed result (missing keys, wrong types or
        shapes, non-finite numbers, a transform that is not a similarity, a box of zero size
        or a reflected one), a bad checkpoint. Nothing is written then.
    regnf.core.file_lock.LockBusy
        Another process kept the stage locked for :data:`~regnf.scene_graph.locking.STAGE_LOCK_TIMEOUT_S`.
    """
    stage_path = Path(stage_path).absolute()
    raw_name = result_json.get("library_name") if isinstance(result_json, Mapping) else None
    shown = raw_name if isinstance(raw_name, str) and raw_name else "?"
    target = L.instance_path(instance_id) if instance_id else f"{L.INSTANCES}/<new {shown} instance>"
    name, M, reg = parse_registration(result_json, False, stage_path, target)
    if not reg.accepted and not force:
        thr = reg.thresholds.get("acceptance_threshold", "?")
        raise StageError(
            stage_path, target,
            f"registration of {name!r} was not accepted (confidence {reg.confidence:.3f} "
            f"below the acceptance threshold {thr}); not written (force it to write anyway)",
        )
    reg.forced = force and not reg.accepted
    ckpt = result_json.get("library_field")
    if ckpt is not None and not isinstance(ckpt, (str, os.PathLike)):
        raise StageError(stage_path, target, f"registration result: 'library_field' must be a path, got {_short(ckpt)}")
    with stage_lock(stage_path):
        scene = read_stage(stage_path, allow_outside=allow_outside)
        if name not in scene.library:
            if not ckpt:
                raise StageError(stage_path, target,
                                 f"{name!r} is not in the library and the result has no library_field")
            rec = field_record(ckpt, f"</{L.prim_name(name)}>", config)
            if rec.name != name:
                raise StageError(ckpt, f"</{L.prim_name(name)}>", f"checkpoint holds {rec.name!r}, the result says {name!r}")
            scene.library[name] = rec
        iid = instance_id or scene.new_instance_id(name)
        if iid in scene.instances:
            raise StageError(stage_path, L.instance_path(iid), "an instance with this id exists already")
        scene.edited_scene = None  # cut for the instances as they were
        scene.instances[iid] = InstanceRecord(iid, name, M, reg)
        write_stage(scene, stage_path)
    return iid
