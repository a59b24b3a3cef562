"""Write then read: every transform to 1e-9, every attribute exactly, the layout docs/design.md
section 1.8 asks for, and xform ops that compose (by hand, with numpy) to the stored 4x4."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
from pxr import Kind, Sdf, Usd, UsdGeom, UsdSemantics

from regnf.scene_graph import RegistrationProvenance, add_instance, read_stage, write_stage
from regnf.scene_graph.xform import OP_ORDER

from .helpers import make_stage, similarity

POSES = {
    "c": similarity(0.3, (1.0, 2.0, 0.0), 1.0),
    "dc": similarity(-2.9, (-1.5, 0.25, 0.0), 0.97),
    "t": similarity(1.234567, (0.1, -1.0, 0.0), 1.05),
}


def _quat_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """Rotation of a unit quaternion, written out independently of regnf.scene_graph.xform."""
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ])


def _registration(name: str) -> RegistrationProvenance:
    return RegistrationProvenance(
        method="regnf", confidence=0.8765432101234, accepted=True, library_name=name,
        scene_to_library=np.linalg.inv(similarity(0.7, (0.3, 0.2, 0.1), 2.5, tilt=0.1)),
        losses={"final_loss": 1.0 / 3.0}, timings={"total": 12.5, "refinement": 7.0 / 3.0},
        thresholds={"inlier_threshold": 0.01}, proposal_center=np.array([0.1, 0.2, 1 / 3]),
        proposal_half_extents=np.array([0.3, 0.4, 0.5]),
        proposal_rotation=similarity(0.4, (0, 0, 0), 1.0)[:3, :3],
    )


@pytest.fixture(scope="module", params=[".usda", ".usdc"])
def stage_path(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp("rt")
    path = make_stage(folder, suffix=request.param)
    add_instance(path, "c", POSES["c"], _registration("c"), instance_id="chair_a")
    add_instance(path, "dc", POSES["dc"], None)
    # A tilted, scaled pose: exercises every quaternion component.
    add_instance(path, "t", similarity(2.0, (3.0, -2.0, 0.5), 1.7, tilt=0.9), _registration("t"))
    return path


def test_round_trip_is_exact(stage_path, tmp_path):
    first = read_stage(stage_path)
    assert list(first.instances) == ["chair_a", "dc_1", "t_1"]
    np.testing.assert_allclose(first.instances["chair_a"].object_to_scene, POSES["c"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(first.instances["dc_1"].object_to_scene, POSES["dc"], rtol=0, atol=1e-9)
    reg = first.instances["chair_a"].registration
    want = _registration("c")
    for f in dataclasses.fields(RegistrationProvenance):
        a, b = getattr(reg, f.name), getattr(want, f.name)
        if isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b, f.name
    assert first.instances["dc_1"].registration is None
    assert first.provenance["test"] == "yes" and first.provenance["n"] == 3
    assert first.provenance["f"] == 0.25 and first.provenance["flag"] is True
    assert first.provenance["sub"] == {"k": "v"}
    # Writing what was read and reading again changes nothing at all.
    again_path = tmp_path / "copy" / f"again{stage_path.suffix}"
    write_stage(first, again_path)
    second = read_stage(again_path)
    _assert_same(first, second)


def _assert_same(a, b):
    assert a.provenance == b.provenance
    for ra, rb in [(a.scene, b.scene)] + [(a.library[k], b.library[k]) for k in a.library]:
        assert (ra.name, ra.label, ra.symmetry_order, ra.provenance) == (rb.name, rb.label, rb.symmetry_order,
                                                                          rb.provenance)
        np.testing.assert_array_equal(ra.to_world, rb.to_world)
        np.testing.assert_array_equal(ra.bounds, rb.bounds)
        np.testing.assert_array_equal(ra.proxy.points, rb.proxy.points)
        np.testing.assert_array_equal(ra.proxy.faces, rb.proxy.faces)
        np.testing.assert_array_equal(ra.proxy.colors, rb.proxy.colors)
        assert ra.checkpoint.read_bytes() == rb.checkpoint.read_bytes()
    assert list(a.instances) == list(b.instances)
    for k, ia in a.instances.items():
        ib = b.instances[k]
        assert ia.library_name == ib.library_name
        np.testing.assert_array_equal(ia.object_to_scene, ib.object_to_scene)
        assert (ia.registration is None) == (ib.registration is None)


def test_field_records_match_checkpoints(stage_path):
    from regnf.io.checkpoint import read_header

    scene = read_stage(stage_path)
    for rec in [scene.scene, *scene.library.values()]:
        header = read_header(rec.checkpoint)
        np.testing.assert_array_equal(rec.to_world, np.array(header["to_world"]))
        np.testing.assert_array_equal(rec.bounds, np.array(header["bounds"]))
        assert rec.label == header["label"] and rec.name == header["name"]
        assert rec.symmetry_order == header["symmetry"]["order"]
        assert rec.provenance == header["provenance"]
        assert rec.checkpoint.parent == stage_path.parent / "fields"


def test_xform_ops_compose_to_the_stored_matrix(stage_path):
    stage = Usd.Stage.Open(str(stage_path))
    for prim in stage.GetPrimAtPath("/World/Instances").GetChildren():
        order = list(prim.GetAttribute("xformOpOrder").Get())
        assert order == list(OP_ORDER)
        t = np.array(prim.GetAttribute("xformOp:translate").Get())
        q = prim.GetAttribute("xformOp:orient").Get()
        s = np.array(prim.GetAttribute("xformOp:scale").Get())
        assert prim.GetAttribute("xformOp:orient").GetTypeName() == Sdf.ValueTypeNames.Quatd
        assert s[0] == s[1] == s[2] > 0
        by_hand = np.eye(4)
        by_hand[:3, :3] = _quat_matrix(q.GetReal(), *q.GetImaginary()) * s[0]
        by_hand[:3, 3] = t
        stored = np.array(prim.GetAttribute("regnf:objectToScene").Get()).T  # Gf rows -> columns
        np.testing.assert_allclose(by_hand, stored, rtol=0, atol=1e-9)
        # ... and USD's own composition of the ops agrees (row-vector convention: transpose).
        usd = np.array(UsdGeom.Xformable(prim).GetLocalTransformation()).T
        np.testing.assert_allclose(usd, stored, rtol=0, atol=1e-9)


def test_stage_layout(stage_path):
    stage = Usd.Stage.Open(str(stage_path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    kind = {p: Usd.ModelAPI(stage.GetPrimAtPath(p)).GetKind()
            for p in ("/World", "/World/Instances", "/World/Scene", "/World/Instances/chair_a")}
    assert kind == {"/World": Kind.Tokens.assembly, "/World/Instances": Kind.Tokens.assembly,
                    "/World/Scene": Kind.Tokens.component, "/World/Instances/chair_a": Kind.Tokens.component}
    data = stage.GetRootLayer().customLayerData["regnf"]
    assert data["formatVersion"] == 1 and data["provenance"]["producer"] == "regnf scene_graph"
    # One asset layer per library object, kind component, with a relative checkpoint path.
    for name in ("c", "dc", "t"):
        lib = Usd.Stage.Open(str(stage_path.parent / "library" / f"{name}.usda"))
        prim = lib.GetDefaultPrim()
        assert Usd.ModelAPI(prim).GetKind() == Kind.Tokens.component
        asset = prim.GetAttribute("regnf:field:checkpoint").Get()
        assert not os.path.isabs(asset.path) and asset.path == f"../fields/{name}.safetensors"
        assert os.path.samefile(asset.resolvedPath, stage_path.parent / "fields" / f"{name}.safetensors")
        labels = UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get()
        assert list(labels) == [{"c": "chair", "dc": "chair", "t": "table"}[name]]
        assert prim.GetAttribute("regnf:field:symmetryOrder").Get() == 1
        mesh = UsdGeom.Mesh(prim.GetChild("Proxy"))
        pts = np.array(mesh.GetPointsAttr().Get())
        ext = np.array(mesh.GetExtentAttr().Get())
        np.testing.assert_array_equal(ext, np.stack([pts.min(0), pts.max(0)]))
        np.testing.assert_array_equal(ext, np.array(UsdGeom.Boundable.ComputeExtentFromPlugins(mesh, 0)))
    scene_prim = stage.GetPrimAtPath("/World/Scene")
    assert list(UsdSemantics.LabelsAPI(scene_prim, "class").GetLabelsAttr().Get()) == ["scene"]
    assert scene_prim.GetAttribute("regnf:field:checkpoint").Get().path == "./fields/scene_field.safetensors"
    # Instances: instanceable, referencing the class's slot, selecting their object.
    prim = stage.GetPrimAtPath("/World/Instances/chair_a")
    assert prim.IsInstance()
    assert prim.GetVariantSet("libraryObject").GetVariantSelection() == "c"
    assert prim.GetAttribute("regnf:registration:method").Get() == "regnf"
    assert prim.GetAttribute("regnf:registration:confidence").Get() == 0.8765432101234
    assert prim.GetAttribute("regnf:registration:timings:total").Get() == 12.5
    assert prim.GetAttribute("regnf:registration:proposal:halfExtents").Get() == (0.3, 0.4, 0.5)
    slot_stage = Usd.Stage.Open(str(stage_path.parent / "slots" / "chair.usda"))
    slot = slot_stage.GetDefaultPrim()
    assert slot.GetVariantSet("libraryObject").GetVariantNames() == ["c", "dc"]
