"""Make and change stages: a new stage from fields, instances by hand or from registrations.

Each operation reads the stage, changes the model, checks it and writes every file in one
transaction: on any error the stage on disk is left exactly as it was.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import trimesh

from . import layout as L
from .errors import StageError
from .fields import ProxyConfig, checkpoint_name, field_record
from .model import ComposedScene, InstanceRecord, RegistrationProvenance
from .usd_read import read_stage
from .usd_write import write_stage

PRODUCER = "regnf scene_graph"


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
    """
    stage_path = Path(stage_path).absolute()
    if stage_path.exists() and not overwrite:
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
    write_stage(ComposedScene(scene, library, {}, prov), stage_path)
    return read_stage(stage_path)


def add_library_object(
    stage_path: str | os.PathLike,
    checkpoint: str | os.PathLike,
    config: ProxyConfig | None = None,
    proxy: trimesh.Trimesh | None = None,
) -> str:
    """Add a library object (and its class's slot variant) to a stage; returns its name."""
    stage_path = Path(stage_path).absolute()
    scene = read_stage(stage_path)
    rec = field_record(checkpoint, "/World/Library", config, proxy)
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
        Prim name; ``<name>_<k>`` by default.
    """
    stage_path = Path(stage_path).absolute()
    scene = read_stage(stage_path)
    iid = instance_id or scene.new_instance_id(library_name)
    if iid in scene.instances:
        raise StageError(stage_path, L.instance_path(iid), "an instance with this id exists already")
    scene.instances[iid] = InstanceRecord(iid, library_name, np.asarray(object_to_scene, dtype=np.float64),
                                          registration)
    write_stage(scene, stage_path)
    return iid


def provenance_from_registration(result: Mapping, forced: bool = False) -> RegistrationProvenance:
    """The provenance kept on an instance, from ``regnf register``'s JSON."""
    box = result.get("proposal_box") or None
    T = result.get("transform_scene_to_library") or {}
    return RegistrationProvenance(
        method=str(result.get("method", "unknown")),
        confidence=float(result.get("confidence", float("nan"))),
        accepted=bool(result.get("accepted", False)),
        library_name=str(result.get("library_name", "")),
        scene_to_library=np.asarray(T.get("matrix", np.eye(4)), dtype=np.float64),
        losses={k: float(v) for k, v in (result.get("losses") or {}).items()},
        timings={k: float(v) for k, v in (result.get("timings") or {}).items()},
        thresholds={k: float(v) for k, v in (result.get("thresholds") or {}).items()
                    if isinstance(v, (int, float))},
        proposal_center=None if box is None else np.asarray(box["center"], dtype=np.float64),
        proposal_half_extents=None if box is None else np.asarray(box["half_extents"], dtype=np.float64),
        proposal_rotation=None if box is None else np.asarray(box["rotation"], dtype=np.float64),
        forced=forced,
    )


def add_instance_from_registration(
    stage_path: str | os.PathLike,
    result_json: Mapping,
    force: bool = False,
    instance_id: str | None = None,
    config: ProxyConfig | None = None,
) -> str:
    """Write a registration (the JSON of ``regnf register``) as an instance; returns its id.

    The library object is added to the stage first if it is not there yet (from the
    result's ``library_field`` checkpoint). A registration that was not accepted
    (confidence below the threshold) is refused unless ``force``.

    Raises
    ------
    StageError
        Not accepted (and not forced), missing keys, a bad transform or checkpoint.
    """
    stage_path = Path(stage_path).absolute()
    name = str(result_json.get("library_name") or "")
    target = L.instance_path(instance_id) if instance_id else f"{L.INSTANCES}/<new {name or '?'} instance>"
    missing = [k for k in ("library_name", "object_to_scene_metres", "accepted", "confidence")
               if k not in result_json]
    if missing:
        raise StageError(stage_path, target, f"the registration result lacks {missing}")
    if not result_json["accepted"] and not force:
        thr = (result_json.get("thresholds") or {}).get("acceptance_threshold", "?")
        raise StageError(
            stage_path, target,
            f"registration of {name!r} was not accepted (confidence {float(result_json['confidence']):.3f} "
            f"below the acceptance threshold {thr}); not written (force it to write anyway)",
        )
    scene = read_stage(stage_path)
    if name not in scene.library:
        ckpt = result_json.get("library_field")
        if not ckpt:
            raise StageError(stage_path, target, f"{name!r} is not in the library and the result has no library_field")
        rec = field_record(ckpt, f"</{L.prim_name(name)}>", config)
        if rec.name != name:
            raise StageError(ckpt, f"</{L.prim_name(name)}>", f"checkpoint holds {rec.name!r}, the result says {name!r}")
        scene.library[name] = rec
    iid = instance_id or scene.new_instance_id(name)
    if iid in scene.instances:
        raise StageError(stage_path, L.instance_path(iid), "an instance with this id exists already")
    M = np.asarray(result_json["object_to_scene_metres"], dtype=np.float64)
    reg = provenance_from_registration(result_json, forced=force and not result_json["accepted"])
    scene.instances[iid] = InstanceRecord(iid, name, M, reg)
    write_stage(scene, stage_path)
    return iid
