"""An exported stage as Blender shows it: Blender's Python module (``bpy``) imports it with its own
USD importer and renders it with Cycles from regnf's cameras, each instance in a colour of its
own; every instance's silhouette must agree with regnf's instance mask of the same view, each
instance must come with its source mesh's materials (colours, texture), and
no vertex of the scene mesh Blender imported may lie inside a removal region (Blender shows the
edit, not the whole scene with the original objects).

Blender runs in a process of its own (``tests/compositor/blender_render.py``).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from regnf.compositor.cameras_io import OrbitConfig, field_bounds_metres, orbit_around_bounds
from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.render_folder import RenderConfig, render_views
from regnf.compositor.scene_mesh import SceneMeshConfig, edited_scene_mesh
from regnf.core.image_io import read_instance_png
from regnf.meshes.source_mesh import keep_source_mesh
from regnf.scene_graph import ProxyMesh, add_instance, export_stage, new_stage
from tests.compositor.golden_scenes import distilled_library, pouf_mesh
from tests.scene_graph.helpers import make_library, similarity

SCRIPT = Path(__file__).with_name("blender_render.py")
ORBIT = OrbitConfig(n=4, width=512, height=384, radius=4.5)
COLORS = {"pouf_1": (1.0, 0.0, 0.0), "pouf_2": (0.0, 1.0, 0.0), "crate_1": (0.0, 0.0, 1.0)}
"""Emission colour of each instance in Blender's render."""


TEXTURE = np.random.default_rng(5).integers(0, 256, (16, 8, 3), dtype=np.uint8)
"""The crate's texture (8 x 16 pixels)."""


def textured_crate() -> trimesh.Trimesh:
    """The crate of the distilled library (a 0.6 x 0.4 x 0.35 m box on z = 0) with uv and a texture."""
    crate = trimesh.creation.box(extents=(0.6, 0.4, 0.35))
    crate.apply_translation((0.0, 0.0, 0.175))
    uv = np.random.default_rng(6).random((len(crate.vertices), 2))
    crate.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(TEXTURE))
    return crate


def linear(srgb: np.ndarray) -> np.ndarray:
    """The sRGB decoding (IEC 61966-2-1): what a renderer's linear colour of an 8-bit colour is."""
    c = np.asarray(srgb, float)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("blender")
    scene, _, proxies = make_library(root, ())
    libs = distilled_library(root)
    # The meshes the fields were distilled from, kept beside them as distillation keeps them: the
    # pouf with its face colours, the crate with a texture.
    keep_source_mesh(pouf_mesh(), libs[0])
    keep_source_mesh(textured_crate(), libs[1])
    stage = root / "stage" / "scene.usda"
    new_stage(stage, scene, libs, proxies={"scene": proxies["scene"]})
    add_instance(stage, "pouf", similarity(0.5, (1.2, -0.5, 0.0), 1.0))
    add_instance(stage, "pouf", similarity(1.5, (-1.2, 0.4, 0.0), 1.25))
    add_instance(stage, "crate", similarity(-0.3, (0.3, 1.2, 0.0), 0.9))
    m = edited_scene_mesh(stage, SceneMeshConfig(cell=0.02, check_points=2000)).mesh
    edited = ProxyMesh(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32),
                       np.asarray(m.visual.vertex_colors)[:, :3].astype(np.float32) / 255)
    return export_stage(stage, root / "export" / "scene.usda", edited_scene=edited, density=500.0)


def test_blender_shows_each_instance_where_regnf_renders_it_and_none_of_the_cut_scene(
        exported: Path, tmp_path: Path) -> None:
    comp = composite_from_stage(exported)
    assert set(comp.instance_ids) == set(COLORS)
    cameras = orbit_around_bounds(field_bounds_metres(comp.field.scene), ORBIT)
    render_views(comp.field, cameras, tmp_path / "regnf", RenderConfig(progress=False))
    checked = 0
    for k, cam in enumerate(cameras):
        job = {"stage": str(exported), "K": cam.K.tolist(), "width": cam.width, "height": cam.height,
               "camera_to_world": cam.camera_to_world.tolist(), "colors": COLORS,
               "places": {n: inst.object_to_scene[:3, 3].tolist() for n, inst in comp.scene.instances.items()},
               "png": str(tmp_path / f"blender_{k}.png"), "scene_points": str(tmp_path / f"scene_{k}.npy"),
               "report": str(tmp_path / f"report_{k}.json")}
        (tmp_path / "job.json").write_text(json.dumps(job))
        run = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "job.json")], capture_output=True,
                             text=True, timeout=600, check=False)
        assert run.returncode == 0, run.stderr[-3000:]
        with Image.open(job["png"]) as im:
            rgb = np.asarray(im.convert("RGB")).astype(np.int64)
        ids = read_instance_png(tmp_path / "regnf" / f"instance_{k:04d}.png")
        for name, colour in COLORS.items():
            blender = np.all(np.abs(rgb - 255 * np.asarray(colour)) < 60, axis=-1)
            ours = ids == comp.instance_ids[name]
            if ours.sum() < 600:  # a sliver behind the room: too few pixels for an IoU
                continue
            iou = (blender & ours).sum() / (blender | ours).sum()
            assert iou >= 0.9, f"view {k}, {name}: IoU {iou:.3f} between Blender's and regnf's silhouettes"
            checked += 1
        report = json.loads(Path(job["report"]).read_text())
        assert report["instances"] == sorted(COLORS), report
        # Blender shows the source meshes with their materials, not the fields' proxies.
        pouf_colors = np.unique(np.asarray(pouf_mesh().visual.face_colors)[:, :3], axis=0) / 255.0
        for name in ("pouf_1", "pouf_2"):
            look = report["looks"][name]
            assert look["vertices"] == len(pouf_mesh().vertices), look
            got = np.asarray(sorted(look["colors"]))
            np.testing.assert_allclose(got, sorted(linear(pouf_colors).tolist()), atol=1e-4)
        crate = report["looks"]["crate_1"]
        assert crate["vertices"] == len(textured_crate().vertices) and crate["images"] == [[8, 16]], crate
        assert report["scene_meshes"] == ["Edited"], report  # the edit, not the whole scene's proxy
        points = np.load(job["scene_points"])
        S = comp.field.scene.to_world.detach().cpu().double().numpy()
        x = torch.as_tensor((points - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T, dtype=torch.float32)
        depth = torch.stack([r.sdf(x) for r in comp.field.removals]).min(dim=0).values * comp.field.scene.world_scale
        assert len(points) > 100 and float(depth.min()) > -1e-3
    assert checked >= 4, "too few instances in view to test anything"
