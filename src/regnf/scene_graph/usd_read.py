"""Read a stage written by :func:`regnf.scene_graph.write_stage` back into a :class:`ComposedScene`.

Everything is checked against our layout, so that a stage written by something else, or
edited by hand into something inconsistent, is reported with the prim and the file at fault:
the ``regnf`` layer data, Z up and metres, every field attribute, asset paths that stay inside
the stage's folder (:mod:`regnf.scene_graph.boundary`), checkpoints that exist and parse, xform ops
that agree with the exact 4x4, registration records that obey :mod:`regnf.scene_graph.checks`.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
from pxr import Ar, Sdf, Tf, Usd, UsdGeom

from regnf.core.preflight import input_file_problem
from regnf.io.checkpoint import CheckpointError, verify_checkpoint

from . import layout as L
from .boundary import Boundary, open_composed
from .checks import check_registration
from .embedded_checkpoint import checkpoint_file, is_embedded
from .errors import StageError
from .model import (
    FORMAT_VERSION,
    ComposedScene,
    FieldRecord,
    InstanceRecord,
    ProxyMesh,
    RegistrationProvenance,
)
from .source_mesh_usd import read_source_mesh
from .xform import OP_ORDER, XformOps, from_usd_matrix, matrix_from_ops

OPS_RTOL = 1e-9
"""The xform ops must compose to the stored 4x4 to this (relative) tolerance."""


def check_stage_file(path: Path) -> None:
    """Refuse a stage path that is not a readable regular file (a folder, a FIFO, a device), unopened.

    Raises
    ------
    StageError
        ``no such stage file``, ``is not a file (a folder)`` and so on.
    """
    problem = input_file_problem(path, "no such stage file")
    if problem is not None:
        raise StageError(path, "", problem)


def open_stage(path: str | os.PathLike, allow_outside: bool = False) -> Usd.Stage:
    """Open a stage fresh from disk (layers already in memory are reloaded), inside its boundary.

    Every sublayer, reference and payload is checked before it is opened
    (:func:`regnf.scene_graph.boundary.open_composed`): one that resolves outside the stage's
    folder (or package) is refused unless ``allow_outside``. A regnf asset layer opened on
    its own (``library/<name>.usda`` or ``slots/<class>.usda``, by the role its
    ``customLayerData`` gives) belongs to the stage one folder up, and has that boundary.

    Raises
    ------
    StageError
        No such file, not a regular file (a folder, FIFO, device), a file USD cannot open, an arc
        outside the boundary.
    """
    path = Path(path).absolute()
    folder = None
    if path.parent.name in (L.LIBRARY_DIR, L.SLOTS_DIR):
        data = dict(root_layer_of(path).customLayerData).get("regnf")
        if isinstance(data, dict) and data.get("role") in (L.ROLE_LIBRARY, L.ROLE_SLOT):
            folder = path.parent.parent
    else:
        check_stage_file(path)
    return open_composed(str(path), Boundary.of(path, allow_outside, folder))


def root_layer_of(path: str | os.PathLike) -> Sdf.Layer:
    """The root layer of the stage at ``path`` alone (nothing it names is opened), fresh from disk.

    Raises
    ------
    StageError
        No such file, not a regular file (a folder, FIFO, device), or USD cannot parse it.
    """
    path = Path(path).absolute()
    check_stage_file(path)
    file = str(path)
    was_loaded = Sdf.Layer.Find(file) is not None
    try:
        layer = Sdf.Layer.FindOrOpen(file)
    except Tf.ErrorException as exc:
        raise StageError(path, "/", f"USD cannot open it: {' '.join(str(exc).split())}") from exc
    if layer is None:
        raise StageError(path, "/", "USD cannot open it")
    if was_loaded:
        layer.Reload(force=True)  # another process may have changed it since it was loaded
    return layer


def replacement_base(stage_path: str | os.PathLike, allow_outside: bool = False) -> Path | None:
    """The stage a replacement layer sits over, or None for a plain stage or package.

    Raises
    ------
    StageError
        The layer cannot be read, is not a regnf stage, or its ``replacementOf`` leaves the
        stage's folder (unless ``allow_outside``); the base is not opened then.
    """
    path = Path(stage_path).absolute()
    if path.suffix == ".usdz":
        return None
    layer = root_layer_of(path)
    ident = replacement_of(layer, regnf_data(layer, str(path)), Boundary.of(path, allow_outside))
    return None if ident is None else Path(ident)


def replacement_of(layer: Sdf.Layer, data: dict, boundary: Boundary) -> str | None:
    """The identifier of the stage a replacement layer sits over (checked), or None.

    Parameters
    ----------
    layer : Sdf.Layer
        The root layer holding ``data``.
    data : dict
        Its ``customLayerData["regnf"]``.
    boundary : Boundary

    Raises
    ------
    StageError
        ``replacementOf`` is not a path, or leaves the boundary; the file is not opened then.
    """
    rel = data.get("replacementOf")
    if rel is None:
        return None
    if not isinstance(rel, str):
        raise StageError(layer.realPath or layer.identifier, "/", f"'replacementOf' must be a path, got {rel!r}")
    return boundary.resolve(layer, rel, "/", "replacementOf (the base stage)")


def _get(prim: Usd.Prim, name: str, file: str, required: bool = True) -> object:
    attr = prim.GetAttribute(name)
    if not attr or not attr.HasAuthoredValue():
        if required:
            raise StageError(file, str(prim.GetPath()),
                             f"has no '{name}' attribute (not written by regnf, or edited)")
        return None
    return attr.Get()


def _proxy(prim: Usd.Prim, file: str, name: str = L.PROXY) -> ProxyMesh:
    mesh = prim.GetChild(name)
    where = f"{prim.GetPath()}/{name}"
    if not mesh or not mesh.IsA(UsdGeom.Mesh):
        raise StageError(file, where, "the field's proxy mesh is missing")
    m = UsdGeom.Mesh(mesh)
    pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float32).reshape(-1, 3)
    counts = np.asarray(m.GetFaceVertexCountsAttr().Get(), dtype=np.int32)
    idx = np.asarray(m.GetFaceVertexIndicesAttr().Get(), dtype=np.int32)
    if len(pts) == 0 or not (counts == 3).all() or idx.size != 3 * counts.size:
        raise StageError(file, where, "the proxy must be a non-empty triangle mesh")
    col = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor")
    colors = None
    if col and col.HasAuthoredValue():
        colors = np.asarray(col.Get(), dtype=np.float32).reshape(-1, 3)
    return ProxyMesh(pts, idx.reshape(-1, 3), colors)


def read_field(prim: Usd.Prim, layer: Sdf.Layer, boundary: Boundary, check_checkpoint: bool = True) -> FieldRecord:
    """The :class:`FieldRecord` of a field prim whose attributes are authored in ``layer``.

    Parameters
    ----------
    prim : Usd.Prim
    layer : Sdf.Layer
        The layer its checkpoint path is authored in (the path is relative to it).
    boundary : Boundary
        Where the checkpoint may lie.
    check_checkpoint : bool
        Parse the checkpoint's header (else only check that it exists).
    """
    file = layer.realPath or layer.identifier
    where = str(prim.GetPath())
    if not prim:
        raise StageError(file, where, "no such prim")
    asset = _get(prim, L.A_CHECKPOINT, file)
    checkpoint = boundary.resolve(layer, asset.path, where, "checkpoint path")
    if check_checkpoint:
        try:
            with checkpoint_file(checkpoint) as ckpt:  # a package's checkpoints are embedded layers
                verify_checkpoint(ckpt)  # header, limits and digest: a stage that reads renders
        except CheckpointError as exc:
            at = checkpoint if is_embedded(checkpoint) else exc.path
            raise StageError(at, where, f"checkpoint referenced by {file}: {exc.problem}") from exc
    elif not Ar.GetResolver().Resolve(checkpoint):
        raise StageError(file, where, f"checkpoint {asset.path!r} does not exist")
    labels = prim.GetAttribute(f"semantics:labels:{L.LABEL_INSTANCE}").Get()
    if not labels or len(labels) != 1:
        raise StageError(file, where, f"needs exactly one class in SemanticsLabelsAPI:{L.LABEL_INSTANCE}")
    if _get(prim, L.A_SYM_AXIS, file) != "z":
        raise StageError(file, where, "only symmetries about z are supported")
    try:
        provenance = json.loads(_get(prim, L.A_FIELD_PROVENANCE, file))
    except json.JSONDecodeError as exc:
        raise StageError(file, where, f"'{L.A_FIELD_PROVENANCE}' is not JSON ({exc})") from exc
    bounds = np.asarray(_get(prim, L.A_BOUNDS, file), dtype=np.float64)
    if bounds.shape != (2, 3):
        raise StageError(file, where, f"'{L.A_BOUNDS}' must hold 2 points, got shape {bounds.shape}")
    _finite(bounds, L.A_BOUNDS, file, where)
    return FieldRecord(
        name=str(_get(prim, L.A_NAME, file)),
        label=str(labels[0]),
        checkpoint=Path(checkpoint),
        to_world=_finite(from_usd_matrix(_get(prim, L.A_TO_WORLD, file)), L.A_TO_WORLD, file, where),
        bounds=bounds,
        symmetry_order=int(_get(prim, L.A_SYM_ORDER, file)),
        provenance=provenance,
        proxy=_proxy(prim, file),
        source_mesh=read_source_mesh(prim, file, boundary),
    )


def _instance_matrix(prim: Usd.Prim, file: str) -> np.ndarray:
    where = str(prim.GetPath())
    M = _finite(from_usd_matrix(_get(prim, L.A_OBJECT_TO_SCENE, file)), L.A_OBJECT_TO_SCENE, file, where)
    order = [str(t) for t in UsdGeom.Xformable(prim).GetXformOpOrderAttr().Get() or []]
    if order != list(OP_ORDER):
        raise StageError(file, where, f"xformOpOrder is {order}, expected {list(OP_ORDER)}")
    t = _finite(np.array(_get(prim, OP_ORDER[0], file), dtype=np.float64), OP_ORDER[0], file, where)
    q = _get(prim, OP_ORDER[1], file)
    quat = _finite(np.array([q.GetReal(), *q.GetImaginary()], dtype=np.float64), OP_ORDER[1], file, where)
    s = _finite(np.array(_get(prim, OP_ORDER[2], file), dtype=np.float64), OP_ORDER[2], file, where)
    if not (s > 0).all() or np.ptp(s) > 1e-12 * s.max():
        raise StageError(file, where, f"scale {s.tolist()} is not uniform and positive")
    if not np.linalg.norm(quat) > 0:
        raise StageError(file, where, f"'{OP_ORDER[1]}' {quat.tolist()} is a zero quaternion")
    composed = matrix_from_ops(XformOps(t, quat, float(s[0])))
    err = np.abs(composed - M).max()
    if not err <= OPS_RTOL * max(1.0, np.abs(M).max()):  # written so that a NaN fails too
        raise StageError(file, where, f"the xform ops disagree with '{L.A_OBJECT_TO_SCENE}' by {err:.3g}")
    return M


def _finite(value: np.ndarray, name: str, file: str, where: str) -> np.ndarray:
    """``value`` (an attribute's numbers) if every entry is finite; else a StageError naming ``name``."""
    if not np.isfinite(value).all():
        raise StageError(file, where, f"'{name}' has non-finite entries: {value.tolist()}")
    return value


def _discovery(prim: Usd.Prim, file: str) -> dict | None:
    """The discovery record of an instance prim (JSON text), None when there is none."""
    text = _get(prim, L.A_DISCOVERY, file, required=False)
    if text is None:
        return None
    try:
        value = json.loads(str(text))
    except json.JSONDecodeError as exc:
        raise StageError(file, str(prim.GetPath()), f"'{L.A_DISCOVERY}' is not JSON ({exc})") from exc
    if not isinstance(value, dict):
        raise StageError(file, str(prim.GetPath()), f"'{L.A_DISCOVERY}' must be a JSON object")
    return value


def _registration(prim: Usd.Prim, file: str) -> RegistrationProvenance | None:
    if not prim.GetAttribute(L.A_METHOD):
        return None

    def group(prefix: str) -> dict[str, float]:
        return {
            a.GetName()[len(prefix):]: float(a.Get())
            for a in prim.GetAttributes()
            if a.GetName().startswith(prefix) and a.HasAuthoredValue()
        }

    box = prim.GetAttribute(L.A_BOX_CENTER)
    rot = _get(prim, L.A_BOX_ROTATION, file, required=False)
    reg = RegistrationProvenance(
        method=str(_get(prim, L.A_METHOD, file)),
        confidence=float(_get(prim, L.A_CONFIDENCE, file)),
        accepted=bool(_get(prim, L.A_ACCEPTED, file)),
        library_name=str(_get(prim, L.A_REG_LIBRARY, file)),
        scene_to_library=from_usd_matrix(_get(prim, L.A_SCENE_TO_LIBRARY, file)),
        losses=group(L.A_LOSSES),
        timings=group(L.A_TIMINGS),
        thresholds=group(L.A_THRESHOLDS),
        proposal_center=np.array(box.Get(), dtype=np.float64) if box else None,
        proposal_half_extents=(np.array(_get(prim, L.A_BOX_HALF, file), dtype=np.float64) if box else None),
        proposal_rotation=(np.array([[rot[i][j] for j in range(3)] for i in range(3)]).T if rot is not None else None),
        forced=bool(_get(prim, L.A_FORCED, file, required=False) or False),
        discovery=_discovery(prim, file),
        warnings=str(_get(prim, L.A_WARNINGS, file, required=False) or "").splitlines(),
    )
    try:
        check_registration(reg)  # the writer's rules: a stage edited by hand must still render
    except ValueError as exc:
        raise StageError(file, str(prim.GetPath()), str(exc)) from exc
    return reg


def regnf_data(layer: Sdf.Layer, file: str) -> dict:
    """The ``customLayerData["regnf"]`` of a root layer, checked."""
    data = dict(layer.customLayerData).get("regnf")
    if not isinstance(data, dict):
        raise StageError(file, "/", "not a regnf stage: customLayerData has no 'regnf' entry "
                         "(written by something else?)")
    version = data.get("formatVersion")
    if version != FORMAT_VERSION:
        raise StageError(file, "/", f"unsupported regnf stage format {version!r} (expected {FORMAT_VERSION})")
    for key in ("library", "slots"):
        if not isinstance(data.get(key), dict):
            raise StageError(file, "/", f"customLayerData 'regnf' lacks its '{key}' table")
    return data


def read_stage(path: str | os.PathLike, check_checkpoints: bool = True, allow_outside: bool = False) -> ComposedScene:
    """Read a regnf stage (.usda, .usdc, a replacement layer, or a .usdz package).

    Parameters
    ----------
    path : str or PathLike
        The root layer.
    check_checkpoints : bool
        Parse every checkpoint's header (inside a package: the embedded one, digest checked).
    allow_outside : bool
        Accept asset paths (layers, checkpoints, ``replacementOf``) that resolve outside the
        stage's folder, or outside the package for a .usdz. By default they are refused
        (:mod:`regnf.scene_graph.boundary`): a stage is its folder.

    Raises
    ------
    StageError
        Naming the file and prim at fault (for an escaping path: the file, the prim and the
        path as authored).
    """
    path = Path(path).absolute()
    boundary = Boundary.of(path, allow_outside)
    root_layer = root_layer_of(path)
    fresh = {root_layer.identifier}
    file = str(path)
    # The regnf tables first, so that a replacement layer over a stage outside the folder is
    # refused before anything it names is opened.
    data = regnf_data(root_layer, file)
    replacement_of(root_layer, data, boundary)
    stage = open_composed(file, boundary, fresh)
    root_layer = stage.GetRootLayer()
    if UsdGeom.GetStageUpAxis(stage) != UsdGeom.Tokens.z:
        raise StageError(file, "/", f"upAxis is {UsdGeom.GetStageUpAxis(stage)}, expected Z")
    if UsdGeom.GetStageMetersPerUnit(stage) != 1.0:
        raise StageError(file, "/", f"metersPerUnit is {UsdGeom.GetStageMetersPerUnit(stage)}, expected 1")
    scene_prim = stage.GetPrimAtPath(L.SCENE)
    if not scene_prim:
        raise StageError(file, L.SCENE, "the scene field prim is missing")
    # The scene's attributes are authored in the base stage (the root, or its sublayer).
    scene_layer = _authoring_layer(scene_prim, L.A_CHECKPOINT) or root_layer
    scene = read_field(scene_prim, scene_layer, boundary, check_checkpoints)

    library: dict[str, FieldRecord] = {}
    for name, rel in sorted(data["library"].items()):
        ident = boundary.resolve(root_layer, _table_path(rel, file, f"library layer of {name!r}"), "/",
                                 f"library layer of {name!r}")
        if not Ar.GetResolver().Resolve(ident):
            raise StageError(ident, "/", f"library layer of {name!r} (listed by {file}) cannot be opened")
        lib_stage = open_composed(ident, boundary, fresh)
        prim = lib_stage.GetDefaultPrim()
        if not prim:
            raise StageError(ident, "/", "library layer has no defaultPrim")
        rec = read_field(prim, lib_stage.GetRootLayer(), boundary, check_checkpoints)
        if rec.name != name:
            raise StageError(ident, str(prim.GetPath()), f"holds {rec.name!r}, listed as {name!r} by {file}")
        library[name] = rec

    for label, rel in sorted(data["slots"].items()):
        ident = boundary.resolve(root_layer, _table_path(rel, file, f"slot layer of class {label!r}"), "/",
                                 f"slot layer of class {label!r}")
        if not Ar.GetResolver().Resolve(ident):
            raise StageError(ident, "/", f"slot layer of class {label!r} (listed by {file}) does not exist")

    instances: dict[str, InstanceRecord] = {}
    inst_root = stage.GetPrimAtPath(L.INSTANCES)
    for prim in inst_root.GetChildren() if inst_root else []:
        where = str(prim.GetPath())
        vset = prim.GetVariantSets().GetVariantSet(L.VARIANT_SET)
        selected = vset.GetVariantSelection() if vset else ""
        if selected not in library:
            raise StageError(file, where, f"selects library object {selected!r}, not one of {sorted(library)}")
        slot_class = prim.GetAttribute(L.A_SLOT_CLASS).Get()
        if slot_class != library[selected].label:
            raise StageError(file, where, f"references the slot of class {slot_class!r} but selects "
                             f"{selected!r}, a {library[selected].label}")
        instances[prim.GetName()] = InstanceRecord(
            id=prim.GetName(),
            library_name=selected,
            object_to_scene=_instance_matrix(prim, file),
            registration=_registration(prim, file),
        )
    provenance = _plain(data.get("provenance", {}))
    density = data.get("physicsDensity")
    if density is not None and not (isinstance(density, (int, float)) and math.isfinite(density) and density > 0):
        raise StageError(file, "/", f"physicsDensity must be a density > 0 in kg / m^3, got {density!r}")
    edited = _proxy(scene_prim, file, L.EDITED) if scene_prim.GetChild(L.EDITED) else None
    return ComposedScene(scene=scene, library=library, instances=instances, provenance=provenance,
                         physics_density=None if density is None else float(density), edited_scene=edited)


def _table_path(rel: object, file: str, what: str) -> str:
    """An entry of the regnf library or slot table, which must be a path (a string)."""
    if not isinstance(rel, str):
        raise StageError(file, "/", f"{what} must be a path, got {rel!r}")
    return rel


def _authoring_layer(prim: Usd.Prim, attr: str) -> Sdf.Layer | None:
    """The strongest layer holding an opinion for ``attr`` on ``prim``."""
    for spec in prim.GetAttribute(attr).GetPropertyStack(Usd.TimeCode.Default()):
        return spec.layer
    return None


def _plain(d: object) -> object:
    """A VtDictionary as plain Python dicts."""
    if isinstance(d, dict):
        return {k: _plain(v) for k, v in d.items()}
    return d
