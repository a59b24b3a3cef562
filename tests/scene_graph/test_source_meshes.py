"""Library objects carry the meshes they were distilled from: a render-purpose ``Source`` mesh with
``UsdPreviewSurface`` materials (face colours, a texture, or a base colour), the field's mesh as
its proxy; the stage reads them back, packages keep the texture, usd-core's validators pass."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from pxr import Usd, UsdGeom, UsdShade

from regnf.meshes.source_mesh import keep_source_mesh, source_mesh_file
from regnf.scene_graph import StageError, add_instance, export_stage, new_stage, read_stage
from regnf.scene_graph import layout as L
from tests.scene_graph.helpers import make_library, similarity
from tests.scene_graph.test_physics_semantics import validation_errors

TEXTURE = np.random.default_rng(2).integers(0, 256, (12, 20, 3), dtype=np.uint8)


def linear(srgb: np.ndarray) -> np.ndarray:
    """sRGB decoding (IEC 61966-2-1)."""
    c = np.asarray(srgb, float)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def two_colour_box() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.9))
    box.apply_translation((0, 0, 0.45))
    colours = np.tile([30, 90, 200, 255], (len(box.faces), 1))
    colours[::3] = [240, 200, 120, 255]
    box.visual.face_colors = colours
    return box


def textured_table() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(1.2, 0.8, 0.75))
    box.apply_translation((0, 0, 0.375))
    uv = np.random.default_rng(3).random((len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(TEXTURE))
    return box


def speckled_sphere() -> trimesh.Trimesh:
    """More colours than materials: one material reading displayColor."""
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    s.visual.face_colors = np.random.default_rng(4).integers(0, 256, (len(s.faces), 4), dtype=np.uint8)
    return s


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("source")
    scene, libs, proxies = make_library(root, ("c", "dc", "t"))
    by_name = {p.stem: p for p in libs}
    keep_source_mesh(two_colour_box(), by_name["c"])
    keep_source_mesh(textured_table(), by_name["t"])
    keep_source_mesh(speckled_sphere(), by_name["dc"])
    path = root / "stage" / "scene.usda"
    new_stage(path, scene, libs, proxies=proxies)
    add_instance(path, "c", similarity(0.5, (2.0, -0.5, 0.0), 1.0))
    add_instance(path, "t", similarity(-0.3, (0.3, 2.0, 0.0), 1.0))
    return path


def composed_meshes(usd: Usd.Stage, instance: str) -> dict[str, Usd.Prim]:
    prim = usd.GetPrimAtPath(L.instance_path(instance))
    return {p.GetName(): p for p in Usd.PrimRange(prim, Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)}


@pytest.mark.parametrize("suffix", [".usda", ".usdz"])
def test_each_instance_renders_its_source_mesh_with_its_materials(stage: Path, tmp_path: Path, suffix: str) -> None:
    out = export_stage(stage, tmp_path / f"scene{suffix}", density=400.0)
    assert validation_errors(out) == []
    usd = Usd.Stage.Open(str(out))
    scene = read_stage(out)
    ids = {r.library_name: i for i, r in scene.instances.items()}
    for name, mesh in (("c", two_colour_box()), ("t", textured_table())):
        meshes = composed_meshes(usd, ids[name])
        assert set(meshes) == {L.SOURCE, L.PROXY}
        source = UsdGeom.Mesh(meshes[L.SOURCE])
        assert source.GetPurposeAttr().Get() == "render" and UsdGeom.Mesh(meshes[L.PROXY]).GetPurposeAttr().Get() == "proxy"
        np.testing.assert_allclose(np.asarray(source.GetPointsAttr().Get()), mesh.vertices, atol=1e-6)
        np.testing.assert_array_equal(np.asarray(source.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), mesh.faces)
        # The collider stays the field's mesh.
        assert meshes[L.PROXY].HasAPI("PhysicsCollisionAPI") and not meshes[L.SOURCE].HasAPI("PhysicsCollisionAPI")
    # The two-coloured box: each face bound to a material of its own colour, linear.
    src = composed_meshes(usd, ids["c"])[L.SOURCE]
    want = linear(np.asarray(two_colour_box().visual.face_colors)[:, :3] / 255.0)
    got = np.zeros_like(want)
    subsets = UsdGeom.Subset.GetAllGeomSubsets(UsdGeom.Imageable(src))
    assert len(subsets) == 2
    for subset in subsets:
        material, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
        shader = UsdShade.Shader(material.GetPrim().GetChild("PreviewSurface"))
        got[np.asarray(subset.GetIndicesAttr().Get())] = shader.GetInput("diffuseColor").Get()
    np.testing.assert_allclose(got, want, atol=1e-6)
    # The table: uv per point and a texture that holds the source's pixels.
    src = composed_meshes(usd, ids["t"])[L.SOURCE]
    np.testing.assert_allclose(np.asarray(UsdGeom.PrimvarsAPI(src).GetPrimvar("st").Get()),
                               np.asarray(textured_table().visual.uv), atol=1e-6)
    material, _ = UsdShade.MaterialBindingAPI(src).ComputeBoundMaterial()
    texture = UsdShade.Shader(material.GetPrim().GetChild("BaseColorTexture"))
    assert texture.GetIdAttr().Get() == "UsdUVTexture"
    with Image.open(io.BytesIO(scene.library["t"].source_mesh.texture)) as im:
        np.testing.assert_array_equal(np.asarray(im.convert("RGB")), TEXTURE)


def test_a_speckled_mesh_gets_one_material_reading_its_display_colour(stage: Path) -> None:
    lib = Usd.Stage.Open(str(stage.parent / L.library_layer("dc")))
    src = lib.GetDefaultPrim().GetChild(L.SOURCE)
    material, _ = UsdShade.MaterialBindingAPI(src).ComputeBoundMaterial()
    reader = material.GetPrim().GetChild("DisplayColorReader")
    assert UsdShade.Shader(reader).GetInput("varname").Get() == "displayColor"
    colours = np.asarray(UsdGeom.PrimvarsAPI(src).GetPrimvar("displayColor").Get())
    want = linear(np.asarray(speckled_sphere().visual.face_colors)[:, :3] / 255.0)
    np.testing.assert_allclose(colours, want, atol=1e-6)


def test_source_meshes_survive_edits_and_read_back_as_written(stage: Path, tmp_path: Path) -> None:
    before = read_stage(stage)
    add_instance(stage, "dc", similarity(1.0, (-1.0, -1.0, 0.0), 1.0))
    after = read_stage(stage)
    for name in ("c", "dc", "t"):
        a, b = before.library[name].source_mesh, after.library[name].source_mesh
        np.testing.assert_array_equal(a.points, b.points)
        for x, y in ((a.face_colors, b.face_colors), (a.uv, b.uv)):
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_allclose(x, y, atol=1e-6)
        assert a.texture == b.texture


def test_a_damaged_source_mesh_is_refused_naming_its_file(tmp_path: Path) -> None:
    scene, libs, proxies = make_library(tmp_path, ("c",))
    source_mesh_file(libs[0]).write_bytes(b"not safetensors")
    with pytest.raises(StageError, match=r"c\.source-mesh\.safetensors.*not a source mesh file"):
        new_stage(tmp_path / "stage" / "scene.usda", scene, libs, proxies=proxies)
    assert not (tmp_path / "stage" / "scene.usda").exists()
