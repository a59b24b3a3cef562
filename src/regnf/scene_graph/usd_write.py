"""Write a :class:`ComposedScene` as USD layers (Sdf API), all files in one transaction.

Files, relative to the stage's folder::

    <stage>.usda|.usdc          /World (assembly): Scene (component), Instances (assembly)
    library/<name>.usda         one asset layer per library object (kind component)
    library/textures/<name>.png the texture of its source mesh, if it has one
    slots/<class>.usda          VariantSet "libraryObject": one variant per library object
    fields/<name>.safetensors   the checkpoints (copied), fields/scene_field.safetensors

Every instance ``/World/Instances/<id>`` references its class's slot, selects a variant and
is instanceable, so that instances of the same object share one prototype.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Vt

from regnf.io.checkpoint import CheckpointError, read_header

from . import layout as L
from .checks import check_registration, check_similarity
from .errors import StageError
from .locking import stage_lock
from .model import (
    FORMAT_VERSION,
    ID_RE,
    NAME_RE,
    ComposedScene,
    FieldRecord,
    InstanceRecord,
    ProxyMesh,
)
from .source_mesh_usd import author_source_mesh
from .transaction import FileTransaction
from .xform import OP_ORDER, ops_from_matrix, to_usd_matrix

STAGE_SUFFIXES = L.STAGE_SUFFIXES
"""Suffixes of a writable stage (export makes .usdz)."""


# -- checks ------------------------------------------------------------------------------------
def check_provenance(value: object, where: str, stage_path: Path) -> None:
    """Stage provenance must fit a USD dictionary: str, int, float, bool or nested dicts."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str) or not k:
                raise StageError(stage_path, "/", f"provenance key {k!r} at {where} is not a non-empty string")
            check_provenance(v, f"{where}.{k}", stage_path)
    elif not isinstance(value, (str, int, float, bool)):
        raise StageError(
            stage_path, "/", f"provenance value at {where} is a {type(value).__name__}; "
            "customLayerData holds strings, numbers, bools and nested dicts only"
        )


def check_scene(scene: ComposedScene, stage_path: Path) -> None:
    """Validate everything before writing anything; raises :class:`StageError`."""
    if stage_path.suffix not in STAGE_SUFFIXES:
        raise StageError(stage_path, "/", f"a stage must end in {' or '.join(STAGE_SUFFIXES)}")
    check_provenance(scene.provenance, "provenance", stage_path)
    d = scene.physics_density
    if d is not None and not (isinstance(d, (int, float)) and np.isfinite(d) and d > 0):
        raise StageError(stage_path, "/", f"the physics density must be > 0 kg / m^3, got {d!r}")
    _check_field(scene.scene, L.SCENE, stage_path)
    for name, rec in scene.library.items():
        where = f"</{L.prim_name(name)}> of {L.library_layer(name)}"
        if name != rec.name or not NAME_RE.match(name) or name == Path(L.SCENE_CHECKPOINT).stem:
            raise StageError(stage_path, where, f"invalid library name {name!r} (letters, digits, _ . -)")
        if not NAME_RE.match(rec.label):
            raise StageError(stage_path, where, f"invalid class label {rec.label!r} (letters, digits, _ . -)")
        _check_field(rec, where, stage_path)
    for iid, inst in scene.instances.items():
        _check_instance(scene, iid, inst, stage_path)


def _check_field(rec: FieldRecord, where: str, stage_path: Path) -> None:
    try:
        read_header(rec.checkpoint)
    except CheckpointError as exc:
        raise StageError(exc.path, where, f"bad checkpoint for stage {stage_path}: {exc.problem}") from exc
    for label, M in (("to_world", rec.to_world),):
        try:
            ops_from_matrix(M)
        except ValueError as exc:
            raise StageError(rec.checkpoint, where, f"{label} is not a similarity: {exc}") from exc
    p = rec.proxy
    if p.points.ndim != 2 or p.points.shape[1] != 3 or len(p.points) == 0 or not np.isfinite(p.points).all():
        raise StageError(stage_path, where, "proxy mesh needs finite (n, 3) points, n > 0")
    if p.faces.ndim != 2 or p.faces.shape[1] != 3 or (p.faces.size and (p.faces.min() < 0 or p.faces.max() >= len(p.points))):
        raise StageError(stage_path, where, "proxy mesh faces must be (m, 3) indices into the points")


def _check_instance(scene: ComposedScene, iid: str, inst: InstanceRecord, stage_path: Path) -> None:
    prim = L.instance_path(iid) if ID_RE.match(iid) else f"{L.INSTANCES}/{iid!r}"
    if iid != inst.id or not ID_RE.match(iid):
        raise StageError(stage_path, prim, f"invalid instance id {iid!r} (a prim name: letters, digits, _)")
    if inst.library_name not in scene.library:
        raise StageError(stage_path, prim, f"library object {inst.library_name!r} is not in the stage's "
                         f"library {sorted(scene.library)}")
    try:
        check_similarity(inst.object_to_scene, "object_to_scene")
        if inst.registration is not None:
            # The reader applies the same rules: what is written here reads back and renders.
            check_registration(inst.registration)
    except ValueError as exc:
        raise StageError(stage_path, prim, str(exc)) from exc


# -- authoring helpers --------------------------------------------------------------------------
def _attr(spec: Sdf.PrimSpec, name: str, type_name: Sdf.ValueTypeName, value: object,
          custom: bool = True, uniform: bool = False) -> Sdf.AttributeSpec:
    var = Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying
    a = Sdf.AttributeSpec(spec, name, type_name, var, custom)
    a.default = value
    return a


def _matrix(M: np.ndarray) -> Gf.Matrix4d:
    return Gf.Matrix4d(to_usd_matrix(M))


def _new_layer(suffix: str = ".usda") -> Sdf.Layer:
    layer = Sdf.Layer.CreateAnonymous(suffix)
    layer.pseudoRoot.SetInfo("upAxis", "Z")
    layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
    return layer


def _author_field(spec: Sdf.PrimSpec, rec: FieldRecord, checkpoint_rel: str) -> None:
    """The field attributes, the semantic class and the proxy mesh on ``spec``."""
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=[f"SemanticsLabelsAPI:{L.LABEL_INSTANCE}"]))
    _attr(spec, f"semantics:labels:{L.LABEL_INSTANCE}", Sdf.ValueTypeNames.TokenArray,
          Vt.TokenArray([rec.label]), custom=False, uniform=True)
    _attr(spec, L.A_CHECKPOINT, Sdf.ValueTypeNames.Asset, Sdf.AssetPath(checkpoint_rel))
    _attr(spec, L.A_TO_WORLD, Sdf.ValueTypeNames.Matrix4d, _matrix(rec.to_world))
    b = np.asarray(rec.bounds, dtype=np.float64)
    _attr(spec, L.A_BOUNDS, Sdf.ValueTypeNames.Double3Array, Vt.Vec3dArray([Gf.Vec3d(*r) for r in b.tolist()]))
    _attr(spec, L.A_NAME, Sdf.ValueTypeNames.String, rec.name)
    _attr(spec, L.A_SYM_AXIS, Sdf.ValueTypeNames.Token, "z")
    _attr(spec, L.A_SYM_ORDER, Sdf.ValueTypeNames.Int, int(rec.symmetry_order))
    _attr(spec, L.A_FIELD_PROVENANCE, Sdf.ValueTypeNames.String, json.dumps(rec.provenance, sort_keys=True))

    _author_mesh(spec, L.PROXY, rec.proxy)


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) float32 unit vertex normals of a triangle mesh: the area-weighted mean of its faces'."""
    p = np.asarray(points, dtype=np.float64)
    tri = p[np.asarray(faces, dtype=np.int64)]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = twice the area
    n = np.zeros_like(p)
    for corner in range(3):  # a loop over the three corners of every face
        np.add.at(n, faces[:, corner], face_n)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.maximum(length, 1e-30), [0.0, 0.0, 1.0]).astype(np.float32)


def _author_mesh(parent: Sdf.PrimSpec, name: str, p: ProxyMesh, purpose: str | None = None) -> Sdf.PrimSpec:
    """A triangle ``Mesh`` child with points, faces, vertex normals, extent and colours."""
    mesh = Sdf.PrimSpec(parent, name, Sdf.SpecifierDef, "Mesh")
    pts = np.ascontiguousarray(p.points, dtype=np.float32)
    faces = np.ascontiguousarray(p.faces, dtype=np.int32)
    _attr(mesh, "points", Sdf.ValueTypeNames.Point3fArray, Vt.Vec3fArray.FromNumpy(pts), custom=False)
    _attr(mesh, "faceVertexCounts", Sdf.ValueTypeNames.IntArray,
          Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)), custom=False)
    _attr(mesh, "faceVertexIndices", Sdf.ValueTypeNames.IntArray,
          Vt.IntArray.FromNumpy(faces.reshape(-1)), custom=False)
    _attr(mesh, "extent", Sdf.ValueTypeNames.Float3Array, Vt.Vec3fArray.FromNumpy(p.extent), custom=False)
    _attr(mesh, "subdivisionScheme", Sdf.ValueTypeNames.Token, "none", custom=False, uniform=True)
    normals = _attr(mesh, "normals", Sdf.ValueTypeNames.Normal3fArray,
                    Vt.Vec3fArray.FromNumpy(vertex_normals(pts, faces)), custom=False)
    normals.SetInfo("interpolation", "vertex")
    if p.colors is not None:
        c = _attr(mesh, "primvars:displayColor", Sdf.ValueTypeNames.Color3fArray,
                  Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(p.colors, dtype=np.float32)), custom=False)
        c.SetInfo("interpolation", "vertex")
    if purpose is not None:
        _attr(mesh, "purpose", Sdf.ValueTypeNames.Token, purpose, custom=False, uniform=True)
    return mesh


def _apply(spec: Sdf.PrimSpec, *schemas: str) -> None:
    """Prepend API schemas to ``spec``, keeping those already applied."""
    old = list(spec.GetInfo("apiSchemas").prependedItems) if spec.HasInfo("apiSchemas") else []
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=old + [s for s in schemas if s not in old]))


def _semantics(spec: Sdf.PrimSpec, taxonomy: str, value: str) -> None:
    """A ``SemanticsLabelsAPI`` label (Isaac Sim 4.5 on) and the same as a legacy ``SemanticsAPI``
    (earlier Isaac Sim Replicator)."""
    _apply(spec, f"SemanticsLabelsAPI:{taxonomy}", f"SemanticsAPI:{taxonomy}")
    _attr(spec, f"semantics:labels:{taxonomy}", Sdf.ValueTypeNames.TokenArray, Vt.TokenArray([value]),
          custom=False, uniform=True)
    _attr(spec, f"semantic:{taxonomy}:params:semanticType", Sdf.ValueTypeNames.String, taxonomy, custom=False)
    _attr(spec, f"semantic:{taxonomy}:params:semanticData", Sdf.ValueTypeNames.String, value, custom=False)


def _collider(mesh: Sdf.PrimSpec, approximation: str, density: float | None = None) -> None:
    """``UsdPhysics`` collider on a mesh: its approximation, and a density when it is a body's."""
    _apply(mesh, "PhysicsCollisionAPI", "PhysicsMeshCollisionAPI", *(["PhysicsMassAPI"] if density else []))
    _attr(mesh, "physics:approximation", Sdf.ValueTypeNames.Token, approximation, custom=False, uniform=True)
    if density:
        _attr(mesh, "physics:density", Sdf.ValueTypeNames.Float, float(density), custom=False)


def library_layer(rec: FieldRecord, density: float | None = None) -> Sdf.Layer:
    """The asset layer of one library object: a component prim holding the field and its proxy
    (a convex-hull collider of ``density`` kg / m^3 when given)."""
    layer = _new_layer()
    name = L.prim_name(rec.name)
    spec = Sdf.PrimSpec(layer, name, Sdf.SpecifierDef, "Xform")
    spec.kind = "component"
    layer.defaultPrim = name
    layer.customLayerData = {"regnf": {"formatVersion": FORMAT_VERSION, "role": L.ROLE_LIBRARY}}
    _author_field(spec, rec, "../" + L.library_checkpoint(rec.name))
    _semantics(spec, L.LABEL_NAME, rec.name)
    if rec.source_mesh is not None:
        # The source mesh is what a viewer renders; the field's mesh stays as its proxy (and collider).
        texture = L.library_texture(rec.name).removeprefix(L.LIBRARY_DIR + "/")
        author_source_mesh(spec, rec.source_mesh, "./" + texture)
        _attr(spec.nameChildren[L.PROXY], "purpose", Sdf.ValueTypeNames.Token, "proxy", custom=False, uniform=True)
    if density:
        _collider(spec.nameChildren[L.PROXY], L.COLLIDER_APPROXIMATION, density)
    return layer


def slot_layer(label: str, names: list[str]) -> Sdf.Layer:
    """The slot asset of one class: a VariantSet with one variant per library object."""
    layer = _new_layer()
    spec = Sdf.PrimSpec(layer, "Slot", Sdf.SpecifierDef, "Xform")
    layer.defaultPrim = "Slot"
    layer.customLayerData = {"regnf": {"formatVersion": FORMAT_VERSION, "role": L.ROLE_SLOT, "class": label}}
    _attr(spec, L.A_SLOT_CLASS, Sdf.ValueTypeNames.String, label)
    vset = Sdf.VariantSetSpec(spec, L.VARIANT_SET)
    for name in names:
        v = Sdf.VariantSpec(vset, name)
        v.primSpec.referenceList.Prepend(Sdf.Reference("../" + L.library_layer(name)))
    spec.variantSetNameList.Prepend(L.VARIANT_SET)
    spec.variantSelections[L.VARIANT_SET] = names[0]
    return layer


def _author_instance(parent: Sdf.PrimSpec, inst: InstanceRecord, label: str, physics: bool = False) -> None:
    spec = Sdf.PrimSpec(parent, inst.id, Sdf.SpecifierDef, "Xform")
    spec.referenceList.Prepend(Sdf.Reference("./" + L.slot_layer(label)))
    spec.variantSelections[L.VARIANT_SET] = inst.library_name
    spec.instanceable = True
    # The class on the instance itself (simulators label instance roots; it is its slot's class,
    # whatever variant is selected); the library object's name comes with the variant.
    _semantics(spec, L.LABEL_INSTANCE, label)
    if physics:
        _apply(spec, "PhysicsRigidBodyAPI")
    ops = ops_from_matrix(inst.object_to_scene)
    _attr(spec, OP_ORDER[0], Sdf.ValueTypeNames.Double3, Gf.Vec3d(*ops.translate.tolist()), custom=False)
    w, x, y, z = ops.orient.tolist()
    _attr(spec, OP_ORDER[1], Sdf.ValueTypeNames.Quatd, Gf.Quatd(w, x, y, z), custom=False)
    _attr(spec, OP_ORDER[2], Sdf.ValueTypeNames.Double3, Gf.Vec3d(ops.scale, ops.scale, ops.scale), custom=False)
    _attr(spec, "xformOpOrder", Sdf.ValueTypeNames.TokenArray, Vt.TokenArray(list(OP_ORDER)),
          custom=False, uniform=True)
    _attr(spec, L.A_OBJECT_TO_SCENE, Sdf.ValueTypeNames.Matrix4d, _matrix(inst.object_to_scene))
    reg = inst.registration
    if reg is None:
        return
    T = Sdf.ValueTypeNames
    _attr(spec, L.A_METHOD, T.String, reg.method)
    _attr(spec, L.A_CONFIDENCE, T.Double, float(reg.confidence))
    _attr(spec, L.A_ACCEPTED, T.Bool, bool(reg.accepted))
    _attr(spec, L.A_FORCED, T.Bool, bool(reg.forced))
    _attr(spec, L.A_REG_LIBRARY, T.String, reg.library_name)
    _attr(spec, L.A_SCENE_TO_LIBRARY, T.Matrix4d, _matrix(reg.scene_to_library))
    for prefix, group in ((L.A_LOSSES, reg.losses), (L.A_TIMINGS, reg.timings), (L.A_THRESHOLDS, reg.thresholds)):
        for k, v in group.items():
            _attr(spec, prefix + k, T.Double, float(v))
    if reg.proposal_center is not None:
        _attr(spec, L.A_BOX_CENTER, T.Double3, Gf.Vec3d(*np.asarray(reg.proposal_center, float).tolist()))
        _attr(spec, L.A_BOX_HALF, T.Double3, Gf.Vec3d(*np.asarray(reg.proposal_half_extents, float).tolist()))
        _attr(spec, L.A_BOX_ROTATION, T.Matrix3d, Gf.Matrix3d(np.asarray(reg.proposal_rotation, float).T.tolist()))
    if reg.discovery is not None:
        _attr(spec, L.A_DISCOVERY, T.String, json.dumps(reg.discovery, sort_keys=True))
    if reg.warnings:
        _attr(spec, L.A_WARNINGS, T.String, "\n".join(reg.warnings))


def root_layer_data(scene: ComposedScene) -> dict:
    """The ``customLayerData["regnf"]`` of the stage: version, library and slots, provenance."""
    return {
        "formatVersion": FORMAT_VERSION,
        "library": {n: "./" + L.library_layer(n) for n in sorted(scene.library)},
        "slots": {c: "./" + L.slot_layer(c) for c in scene.classes()},
        "provenance": scene.provenance,
        **({"physicsDensity": float(scene.physics_density)} if scene.physics_density else {}),
    }


def stage_layer(scene: ComposedScene, suffix: str = ".usda") -> Sdf.Layer:
    """The root layer: /World with the scene field and the instances."""
    layer = _new_layer(suffix)
    world = Sdf.PrimSpec(layer, "World", Sdf.SpecifierDef, "Xform")
    world.kind = "assembly"
    layer.defaultPrim = "World"
    layer.customLayerData = {"regnf": root_layer_data(scene)}
    sc = Sdf.PrimSpec(world, "Scene", Sdf.SpecifierDef, "Xform")
    sc.kind = "component"
    _author_field(sc, scene.scene, "./" + L.SCENE_CHECKPOINT)
    if scene.edited_scene is not None:
        # The edit is what a viewer shows (render); the whole scene stays as the proxy to switch to.
        _attr(sc.nameChildren[L.PROXY], "purpose", Sdf.ValueTypeNames.Token, "proxy", custom=False, uniform=True)
        edited = _author_mesh(sc, L.EDITED, scene.edited_scene, purpose="render")
        rel = Sdf.RelationshipSpec(edited, "proxyPrim", custom=False)
        rel.targetPathList.Prepend(sc.path.AppendChild(L.PROXY))
        if scene.physics_density:  # what the objects stand on: a static triangle-mesh collider
            _collider(edited, "none")
    inst_root = Sdf.PrimSpec(world, "Instances", Sdf.SpecifierDef, "Xform")
    inst_root.kind = "assembly"
    for inst in scene.instances.values():
        _author_instance(inst_root, inst, scene.library[inst.library_name].label, bool(scene.physics_density))
    return layer


def write_stage(scene: ComposedScene, stage_path: str | os.PathLike) -> list[Path]:
    """Write ``scene`` as a stage at ``stage_path`` (.usda or .usdc) with its assets beside it.

    Everything is checked first, then every file is written to a temporary and the set is
    moved into place (the root layer last); on any error nothing on disk changes. The stage
    folder's lock (:func:`regnf.scene_graph.locking.stage_lock`) is held meanwhile; an edit that
    read the stage holds it already, from before its read.

    Returns
    -------
    list of Path
        The files that changed.

    Raises
    ------
    StageError
        Bad names, a missing or corrupted checkpoint, a transform that is not a similarity, a
        registration record :func:`regnf.scene_graph.checks.check_registration` refuses...
    regnf.core.file_lock.LockBusy
        Another process kept the stage's folder locked for too long.
    """
    stage_path = Path(stage_path).absolute()
    check_scene(scene, stage_path)
    root = stage_path.parent
    with stage_lock(stage_path, create=True):
        tx = FileTransaction()
        try:
            tx.copy(scene.scene.checkpoint, root / L.SCENE_CHECKPOINT)
            for name in sorted(scene.library):
                rec = scene.library[name]
                tx.copy(rec.checkpoint, root / L.library_checkpoint(name))
                library_layer(rec, scene.physics_density).Export(str(tx.temp_path(root / L.library_layer(name))))
                if rec.source_mesh is not None and rec.source_mesh.texture is not None:
                    tx.write_bytes(root / L.library_texture(name), rec.source_mesh.texture)
            for label, names in scene.classes().items():
                slot_layer(label, names).Export(str(tx.temp_path(root / L.slot_layer(label))))
            stage_layer(scene, stage_path.suffix).Export(str(tx.temp_path(stage_path)))
        except BaseException:
            tx.abort()
            raise
        return tx.commit()
