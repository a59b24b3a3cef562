"""Read a stage written by :func:`scene_graph.write_stage` back into a :class:`ComposedScene`.

Everything is checked against our layout, so that a stage written by something else, or
edited by hand into something inconsistent, is reported with the prim and the file at fault:
the ``regnf`` layer data, Z up and metres, every field attribute, asset paths that stay inside
the stage's folder, checkpoints that exist and parse, xform ops that agree with the exact 4x4.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from pxr import Ar, Sdf, Tf, Usd, UsdGeom

from neural_fields.checkpoint import CheckpointError, read_header

from . import layout as L
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
from .xform import OP_ORDER, XformOps, from_usd_matrix, matrix_from_ops

OPS_RTOL = 1e-9
"""The xform ops must compose to the stored 4x4 to this (relative) tolerance."""


def open_stage(path: str | os.PathLike) -> Usd.Stage:
    """Open a stage fresh from disk (layers already in memory are reloaded)."""
    path = Path(path)
    if not path.is_file():
        raise StageError(path, "/", "no such stage file")
    loaded = {layer.identifier for layer in Sdf.Layer.GetLoadedLayers()}
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise StageError(path, "/", f"USD cannot open it: {exc}") from exc
    if stage is None:
        raise StageError(path, "/", "USD cannot open it")
    for layer in stage.GetUsedLayers():
        if layer.identifier in loaded and not layer.anonymous:
            layer.Reload(force=True)
    return stage


def _inside(root: Path, identifier: str) -> bool:
    """Whether a resolved asset identifier lies inside ``root`` (or inside its package)."""
    if identifier.endswith("]") and "[" in identifier:  # a file inside a .usdz package
        inner = identifier[identifier.index("[") + 1 : -1]
        return not Path(inner).is_absolute() and ".." not in Path(inner).parts
    try:
        real = Path(os.path.realpath(identifier))
        return real.is_relative_to(Path(os.path.realpath(root)))
    except ValueError:
        return False


def anchored(layer: Sdf.Layer, asset: str, root: Path, owner: str, what: str) -> str:
    """Resolve ``asset`` relative to ``layer``; refuse paths that escape ``root``."""
    if not asset:
        raise StageError(layer.realPath or layer.identifier, owner, f"{what} is empty")
    ident = layer.ComputeAbsolutePath(asset)
    if Path(asset).is_absolute() or not _inside(root, ident):
        raise StageError(layer.realPath or layer.identifier, owner,
                         f"{what} {asset!r} escapes the stage's folder {root}")
    return ident


def _get(prim: Usd.Prim, name: str, file: str, required: bool = True) -> object:
    attr = prim.GetAttribute(name)
    if not attr or not attr.HasAuthoredValue():
        if required:
            raise StageError(file, str(prim.GetPath()),
                             f"has no '{name}' attribute (not written by regnf, or edited)")
        return None
    return attr.Get()


def _proxy(prim: Usd.Prim, file: str) -> ProxyMesh:
    mesh = prim.GetChild(L.PROXY)
    where = f"{prim.GetPath()}/{L.PROXY}"
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


def read_field(prim: Usd.Prim, layer: Sdf.Layer, root: Path, check_checkpoint: bool = True) -> FieldRecord:
    """The :class:`FieldRecord` of a field prim whose attributes are authored in ``layer``."""
    file = layer.realPath or layer.identifier
    where = str(prim.GetPath())
    if not prim:
        raise StageError(file, where, "no such prim")
    asset = _get(prim, L.A_CHECKPOINT, file)
    checkpoint = anchored(layer, asset.path, root, where, "checkpoint path")
    if check_checkpoint:
        try:
            with checkpoint_file(checkpoint) as ckpt:  # a package's checkpoints are embedded layers
                read_header(ckpt)
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
    return FieldRecord(
        name=str(_get(prim, L.A_NAME, file)),
        label=str(labels[0]),
        checkpoint=Path(checkpoint),
        to_world=from_usd_matrix(_get(prim, L.A_TO_WORLD, file)),
        bounds=bounds,
        symmetry_order=int(_get(prim, L.A_SYM_ORDER, file)),
        provenance=provenance,
        proxy=_proxy(prim, file),
    )


def _instance_matrix(prim: Usd.Prim, file: str) -> np.ndarray:
    where = str(prim.GetPath())
    M = from_usd_matrix(_get(prim, L.A_OBJECT_TO_SCENE, file))
    order = [str(t) for t in UsdGeom.Xformable(prim).GetXformOpOrderAttr().Get() or []]
    if order != list(OP_ORDER):
        raise StageError(file, where, f"xformOpOrder is {order}, expected {list(OP_ORDER)}")
    t = np.array(_get(prim, OP_ORDER[0], file), dtype=np.float64)
    q = _get(prim, OP_ORDER[1], file)
    s = np.array(_get(prim, OP_ORDER[2], file), dtype=np.float64)
    if not (s > 0).all() or np.ptp(s) > 1e-12 * s.max():
        raise StageError(file, where, f"scale {s.tolist()} is not uniform and positive")
    quat = np.array([q.GetReal(), *q.GetImaginary()], dtype=np.float64)
    composed = matrix_from_ops(XformOps(t, quat, float(s[0])))
    err = np.abs(composed - M).max()
    if err > OPS_RTOL * max(1.0, np.abs(M).max()):
        raise StageError(file, where, f"the xform ops disagree with '{L.A_OBJECT_TO_SCENE}' by {err:.3g}")
    return M


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
    return RegistrationProvenance(
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
    )


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


def read_stage(path: str | os.PathLike, check_checkpoints: bool = True) -> ComposedScene:
    """Read a regnf stage (.usda, .usdc, a replacement layer, or a .usdz package).

    Parameters
    ----------
    path : str or PathLike
        The root layer.
    check_checkpoints : bool
        Parse every checkpoint's header (inside a package: the embedded one, digest checked).

    Raises
    ------
    StageError
        Naming the file and prim at fault.
    """
    path = Path(path).absolute()
    stage = open_stage(path)
    root_layer = stage.GetRootLayer()
    file = str(path)
    data = regnf_data(root_layer, file)
    if UsdGeom.GetStageUpAxis(stage) != UsdGeom.Tokens.z:
        raise StageError(file, "/", f"upAxis is {UsdGeom.GetStageUpAxis(stage)}, expected Z")
    if UsdGeom.GetStageMetersPerUnit(stage) != 1.0:
        raise StageError(file, "/", f"metersPerUnit is {UsdGeom.GetStageMetersPerUnit(stage)}, expected 1")
    root = path.parent
    scene_prim = stage.GetPrimAtPath(L.SCENE)
    if not scene_prim:
        raise StageError(file, L.SCENE, "the scene field prim is missing")
    # The scene's attributes are authored in the base stage (the root, or its sublayer).
    scene_layer = _authoring_layer(scene_prim, L.A_CHECKPOINT) or root_layer
    scene = read_field(scene_prim, scene_layer, root, check_checkpoints)

    library: dict[str, FieldRecord] = {}
    for name, rel in sorted(data["library"].items()):
        ident = anchored(root_layer, rel, root, "/", f"library layer of {name!r}")
        lib_stage = Usd.Stage.Open(ident) if Ar.GetResolver().Resolve(ident) else None
        if lib_stage is None:
            raise StageError(ident, "/", f"library layer of {name!r} (listed by {file}) cannot be opened")
        prim = lib_stage.GetDefaultPrim()
        if not prim:
            raise StageError(ident, "/", "library layer has no defaultPrim")
        rec = read_field(prim, lib_stage.GetRootLayer(), root, check_checkpoints)
        if rec.name != name:
            raise StageError(ident, str(prim.GetPath()), f"holds {rec.name!r}, listed as {name!r} by {file}")
        library[name] = rec

    for label, rel in sorted(data["slots"].items()):
        ident = anchored(root_layer, rel, root, "/", f"slot layer of class {label!r}")
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
    return ComposedScene(scene=scene, library=library, instances=instances, provenance=provenance)


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
