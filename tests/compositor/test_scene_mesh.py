"""The edited scene's mesh: no vertex inside a removal region, on the masked field's zero set,
and in an exported stage as the render-purpose mesh beside the whole scene's proxy.

Instances are placed where the scene field has surface (found by meshing the field here), so
that the whole scene's mesh does cross their removal regions: the test of the edit can fail.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from pxr import Usd, UsdGeom

from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.scene_mesh import SceneMeshConfig, edited_scene_mesh
from regnf.meshes.meshing import extract_mesh
from regnf.scene_graph import ProxyMesh, add_instance, export_stage, read_stage
from regnf.scene_graph import layout as L
from tests.scene_graph.helpers import make_stage, similarity

CELL = 0.05
"""Metres: coarse, so the tests stay quick on the tiny fields."""


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = make_stage(tmp_path_factory.mktemp("scene_mesh"), names=("c", "dc", "t"))
    scene = composite_from_stage(path).field.scene
    whole = extract_mesh(scene, resolution=48, with_color=False, in_world=True)
    v = np.asarray(whole.vertices)
    # Two places on the scene's surface, far apart, for a chair and a table.
    first = v[np.argmax(v[:, 0])]
    second = v[np.argmin(v[:, 0])]
    add_instance(path, "c", similarity(0.4, (first[0] - 0.1, first[1], first[2] - 0.3), 1.0))
    add_instance(path, "t", similarity(-0.2, (second[0] + 0.2, second[1], second[2] - 0.3), 1.0))
    return path


def inside_regions(stage: Path, points_world: np.ndarray, depth: float = 1e-3) -> np.ndarray:
    """(n,) bool: more than ``depth`` metres inside a removal region of the stage's composite
    (the cut faces lie on the regions' boundaries, to float precision)."""
    comp = composite_from_stage(stage).field
    S = comp.scene.to_world.detach().cpu().double().numpy()
    x = (points_world - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    xt = torch.as_tensor(x, dtype=torch.float32)
    inside = torch.zeros(len(x), dtype=torch.bool)
    for region in comp.removals:
        inside |= region.sdf(xt) * comp.scene.world_scale < -depth
    return inside.numpy()


def test_no_triangle_of_the_edit_lies_in_a_removal_region(stage: Path) -> None:
    result = edited_scene_mesh(stage, SceneMeshConfig(cell=CELL, check_points=20000))
    mesh = result.mesh
    assert result.removals >= 2
    # The whole scene crosses the regions (so this test can fail) ...
    scene_only = composite_from_stage(stage).field.scene
    full = extract_mesh(scene_only, resolution=int(np.ceil(3.0 / CELL)), with_color=False, in_world=True)
    assert inside_regions(stage, np.asarray(full.vertices)).sum() > 20
    # ... the edit does not: no vertex inside a region, and a face across the crease where a
    # region cuts the surface cuts that corner by less than half a cell.
    assert not inside_regions(stage, np.asarray(mesh.vertices)).any()
    assert not inside_regions(stage, mesh.triangles_center, depth=0.5 * CELL).any()
    # On the masked field's surface: the Newton steps put it within a fraction of the cell.
    assert result.distance_p99 < 0.1 * CELL and result.distance_max < CELL
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)


def test_an_export_shows_the_edit_and_keeps_the_whole_scene_as_its_proxy(stage: Path, tmp_path: Path) -> None:
    result = edited_scene_mesh(stage, SceneMeshConfig(cell=CELL, check_points=2000))
    m = result.mesh
    edited = ProxyMesh(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32),
                       np.asarray(m.visual.vertex_colors)[:, :3].astype(np.float32) / 255)
    out = export_stage(stage, tmp_path / "out" / "scene.usda", edited_scene=edited)
    again = read_stage(out)
    np.testing.assert_array_equal(again.edited_scene.points, edited.points)
    np.testing.assert_array_equal(again.edited_scene.faces, edited.faces)
    usd = Usd.Stage.Open(str(out))
    proxy, render = (usd.GetPrimAtPath(f"{L.SCENE}/{n}") for n in (L.PROXY, L.EDITED))
    assert UsdGeom.Imageable(proxy).GetPurposeAttr().Get() == "proxy"
    assert UsdGeom.Imageable(render).GetPurposeAttr().Get() == "render"
    assert UsdGeom.Imageable(render).GetProxyPrimRel().GetTargets() == [proxy.GetPath()]
    # Every mesh carries vertex normals, unit length.
    for prim in Usd.PrimRange(usd.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            n = np.asarray(mesh.GetNormalsAttr().Get())
            assert len(n) == len(mesh.GetPointsAttr().Get()) and mesh.GetNormalsInterpolation() == "vertex"
            np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    # Any change of the instances drops the edit: it was cut for the old ones.
    add_instance(out, "dc", similarity(0.0, (0.0, 0.0, 0.0), 1.0))
    assert read_stage(out).edited_scene is None


def test_selecting_another_variant_in_plain_usd_changes_the_composed_mesh(stage: Path) -> None:
    usd = Usd.Stage.Open(str(stage))
    scene = read_stage(stage)
    (chair,) = [i for i, r in scene.instances.items() if r.library_name == "c"]
    prim = usd.GetPrimAtPath(f"{L.INSTANCES}/{chair}")

    def composed_points() -> np.ndarray:
        meshes = [p for p in Usd.PrimRange(prim, Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)]
        assert len(meshes) == 1
        return np.asarray(UsdGeom.Mesh(meshes[0]).GetPointsAttr().Get())

    np.testing.assert_allclose(composed_points(), scene.library["c"].proxy.points)
    prim.GetVariantSets().GetVariantSet(L.VARIANT_SET).SetVariantSelection("dc")
    np.testing.assert_allclose(composed_points(), scene.library["dc"].proxy.points)


def test_an_export_can_carry_finer_library_meshes(stage: Path, tmp_path: Path) -> None:
    from regnf.scene_graph import StageError

    tetra = ProxyMesh(np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.3]], np.float32),
                      np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32), None)
    out = export_stage(stage, tmp_path / "fine" / "scene.usda", library_meshes={"c": tetra})
    again = read_stage(out)
    np.testing.assert_array_equal(again.library["c"].proxy.points, tetra.points)
    np.testing.assert_array_equal(again.library["t"].proxy.points, read_stage(stage).library["t"].proxy.points)
    with pytest.raises(StageError, match="no library object 'chair'"):
        export_stage(stage, tmp_path / "bad" / "scene.usda", library_meshes={"chair": tetra})
