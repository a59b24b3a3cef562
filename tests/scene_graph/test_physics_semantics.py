"""What simulators read from an exported stage: semantics, rigid bodies, colliders, and a clean
validation by usd-core's own validators (the ones ``usdchecker`` runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdPhysics, UsdSemantics, UsdValidation

from regnf.cli.app import main
from regnf.scene_graph import ProxyMesh, add_instance, export_stage, read_stage
from regnf.scene_graph import layout as L
from tests.scene_graph.helpers import OBJECTS, make_stage, similarity


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = make_stage(tmp_path_factory.mktemp("physics"), names=("c", "dc", "t"))
    add_instance(path, "c", similarity(0.5, (2.0, -0.5, 0.0), 1.0))
    add_instance(path, "dc", similarity(1.5, (-2.0, 0.4, 0.0), 1.2))
    add_instance(path, "t", similarity(-0.3, (0.3, 2.0, 0.0), 1.0))
    return path


def validation_errors(path: Path) -> list[str]:
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors]


def floor_mesh() -> ProxyMesh:
    pts = np.array([[-3, -3, 0], [3, -3, 0], [3, 3, 0], [-3, 3, 0]], dtype=np.float32)
    return ProxyMesh(pts, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32), None)


@pytest.mark.parametrize("suffix", [".usdz", ".usda"])
def test_every_instance_is_a_labelled_rigid_body_with_a_collider_of_the_density(
        stage: Path, tmp_path: Path, suffix: str) -> None:
    out = export_stage(stage, tmp_path / f"export{suffix}", edited_scene=floor_mesh(), density=420.0)
    assert validation_errors(out) == []
    usd = Usd.Stage.Open(str(out))
    scene = read_stage(stage)
    assert read_stage(out).physics_density == 420.0
    for iid, inst in scene.instances.items():
        prim = usd.GetPrimAtPath(f"{L.INSTANCES}/{iid}")
        assert prim.HasAPI(UsdPhysics.RigidBodyAPI)
        label = OBJECTS[inst.library_name][0]
        assert UsdSemantics.LabelsAPI(prim, "class").GetLabelsAttr().Get() == [label]
        assert prim.GetAttribute("semantic:class:params:semanticData").Get() == label
        # The library object's name and its collider come with the selected variant.
        assert UsdSemantics.LabelsAPI(prim, "name").GetLabelsAttr().Get() == [inst.library_name]
        (mesh,) = [p for p in Usd.PrimRange(prim, Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)]
        assert mesh.HasAPI(UsdPhysics.CollisionAPI) and mesh.HasAPI(UsdPhysics.MassAPI)
        assert UsdPhysics.MeshCollisionAPI(mesh).GetApproximationAttr().Get() == "convexHull"
        assert UsdPhysics.MassAPI(mesh).GetDensityAttr().Get() == pytest.approx(420.0)
    floor = usd.GetPrimAtPath(f"{L.SCENE}/{L.EDITED}")
    assert floor.HasAPI(UsdPhysics.CollisionAPI) and not floor.HasAPI(UsdPhysics.RigidBodyAPI)
    assert UsdPhysics.MeshCollisionAPI(floor).GetApproximationAttr().Get() == "none"


def test_a_stage_without_a_density_has_no_physics(stage: Path, tmp_path: Path) -> None:
    out = export_stage(stage, tmp_path / "plain.usda")
    usd = Usd.Stage.Open(str(out))
    assert not any(p.HasAPI(UsdPhysics.RigidBodyAPI) or p.HasAPI(UsdPhysics.CollisionAPI)
                   for p in Usd.PrimRange(usd.GetPseudoRoot(), Usd.TraverseInstanceProxies()))
    assert validation_errors(out) == []


@pytest.mark.parametrize("density", ["0", "-5", "nan"])
def test_export_refuses_a_density_that_is_not_positive_in_one_line(
        stage: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], density: str) -> None:
    out = tmp_path / "bad.usdz"
    assert main(["stage", "export", str(stage), "--usdz", str(out), "--density", density]) == 1
    err = capsys.readouterr().err.strip()
    assert "--density must be > 0" in err and len(err.splitlines()) == 1 and not out.exists()


def test_export_refuses_a_negative_library_cell_in_one_line(
        stage: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bad.usdz"
    assert main(["stage", "export", str(stage), "--usdz", str(out), "--library-cell", "-0.01"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--library-cell must be >= 0" in err and len(err.splitlines()) == 1 and not out.exists()
