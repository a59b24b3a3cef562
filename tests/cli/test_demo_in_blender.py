"""The demo's package as Blender shows it: ``regnf demo`` runs (into a fresh cache), then Blender's
Python module imports its ``.usdz`` with its own USD importer and renders it from regnf's
cameras (``tests/compositor/blender_render.py``, in a process of its own).

- Every substituted chair's whole silhouette (the chair alone) agrees with regnf's mask of it
  traced alone, IoU >= 0.9 in every view that shows it.
- Its visible silhouette agrees with regnf's instance mask, IoU >= 0.9, wherever at least half
  of it is visible: Blender shows the source mesh and regnf the field distilled from it, whose
  edges are rounded by a few millimetres, so a chair seen mostly through the slats of another
  is bounded by edges that are not its own.
- Every chair comes with its source mesh's materials.
- No vertex of the scene mesh Blender shows lies inside a removal region (the original,
  captured chairs are gone).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from regnf.cli.demo import DemoConfig, run_demo
from regnf.compositor.cameras_io import OrbitConfig, field_bounds_metres, orbit_around_bounds
from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.render_folder import RenderConfig, render_views
from regnf.core.image_io import read_instance_png
from regnf.datasets.full_masks import full_masks
from regnf.synthetic.cache import Cache
from regnf.synthetic.library import make_library_object

SCRIPT = Path(__file__).parents[1] / "compositor" / "blender_render.py"
ORBIT = OrbitConfig(n=3, width=512, height=384)
PALETTE = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 0.0), (0.0, 1.0, 1.0), (1.0, 0.0, 1.0)]
"""Emission colours of the instances in Blender's render."""


def linear(srgb: np.ndarray) -> np.ndarray:
    """sRGB decoding (IEC 61966-2-1): the linear colour a renderer uses for an 8-bit colour."""
    c = np.asarray(srgb, float)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@pytest.fixture(scope="module")
def demo_usdz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("demo")
    config = DemoConfig()
    run_demo(root / "out", config, Cache(root / "cache", progress=False))
    return root / "out" / f"{config.room}.usdz"


def test_blender_shows_the_demos_substituted_chairs_with_their_materials_and_none_of_the_originals(
        demo_usdz: Path, tmp_path: Path) -> None:
    comp = composite_from_stage(demo_usdz)
    names = sorted(comp.instance_ids)
    assert len(names) == 5, names  # the demo finds and substitutes all five chairs
    colors = {n: PALETTE[i] for i, n in enumerate(names)}
    cameras = orbit_around_bounds(field_bounds_metres(comp.field.scene), ORBIT)
    render = RenderConfig(progress=False)
    render_views(comp.field, cameras, tmp_path / "regnf", render)
    whole = full_masks(tmp_path / "regnf", comp.field, cameras, render.sphere)
    S = comp.field.scene.to_world.detach().cpu().double().numpy()
    checked = set()
    for k, cam in enumerate(cameras):
        job = {"stage": str(demo_usdz), "K": cam.K.tolist(), "width": cam.width, "height": cam.height,
               "camera_to_world": cam.camera_to_world.tolist(), "colors": colors,
               "places": {n: inst.object_to_scene[:3, 3].tolist() for n, inst in comp.scene.instances.items()},
               "png": str(tmp_path / f"blender_{k}.png"), "scene_points": str(tmp_path / f"scene_{k}.npy"),
               "report": str(tmp_path / f"report_{k}.json"),
               "alone": {n: str(tmp_path / f"alone_{k}_{n}.png") for n in names}}
        (tmp_path / "job.json").write_text(json.dumps(job))
        run = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "job.json")], capture_output=True,
                             text=True, timeout=900, check=False)
        assert run.returncode == 0, run.stderr[-3000:]
        with Image.open(job["png"]) as im:
            rgb = np.asarray(im.convert("RGB")).astype(np.int64)
        ids = read_instance_png(tmp_path / "regnf" / f"instance_{k:04d}.png")
        for name, colour in colors.items():
            with Image.open(job["alone"][name]) as im:
                alone = np.all(np.abs(np.asarray(im.convert("RGB")).astype(np.int64) - 255 * np.asarray(colour)) < 60,
                               axis=-1)
            full = whole[comp.instance_ids[name]][k]
            if full.sum() < 600:  # outside this view, or a sliver at its edge
                continue
            iou = (alone & full).sum() / (alone | full).sum()
            assert iou >= 0.9, f"view {k}, {name} alone: IoU {iou:.3f} between Blender's and regnf's silhouettes"
            checked.add(name)
            blender = np.all(np.abs(rgb - 255 * np.asarray(colour)) < 60, axis=-1)
            ours = ids == comp.instance_ids[name]
            if ours.sum() >= 0.5 * full.sum():
                iou = (blender & ours).sum() / (blender | ours).sum()
                assert iou >= 0.9, f"view {k}, {name}: IoU {iou:.3f} between the visible silhouettes"
        report = json.loads(Path(job["report"]).read_text())
        assert report["instances"] == names and report["scene_meshes"] == ["Edited"], report
        for name in names:  # each chair is its library object's source mesh, in its colours
            mesh = make_library_object(comp.scene.instances[name].library_name).mesh
            look = report["looks"][name]
            assert look["vertices"] == len(mesh.vertices), (name, look)
            want = linear(np.unique(np.asarray(mesh.visual.face_colors)[:, :3], axis=0) / 255.0)
            np.testing.assert_allclose(np.asarray(sorted(look["colors"])), sorted(want.tolist()), atol=1e-4)
        points = np.load(job["scene_points"])
        x = torch.as_tensor((points - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T, dtype=torch.float32)
        depth = torch.stack([r.sdf(x) for r in comp.field.removals]).min(dim=0).values * comp.field.scene.world_scale
        assert len(points) > 1000 and float(depth.min()) > -1e-3, float(depth.min())
    assert checked == set(names), f"chairs never checked in any view: {set(names) - checked}"
