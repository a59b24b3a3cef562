"""BOP output of ``regnf generate``, read back by a reader written here from the BOP format's text.

The reader knows only the format: ``models/models_info.json`` and ``obj_XXXXXX.ply`` in
millimetres, and per scene ``scene_camera.json`` (``cam_K``, ``depth_scale``),
``scene_gt.json`` (``obj_id``, ``cam_R_m2c``, ``cam_t_m2c``), ``scene_gt_info.json`` and the
masks ``mask[_visib]/<image>_<gt>.png``. The truths: the variant's own instance and depth
images (read with PIL), the models' vertices (read with trimesh), and silhouettes drawn here by
projecting each model with its pose: they must match the whole-object masks.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from regnf.compositor.cameras_io import OrbitConfig
from regnf.core.executors import ExecutorConfig
from regnf.datasets.generation import GenerateConfig, generate
from regnf.scene_graph import add_instance, new_stage
from tests.compositor.golden_scenes import distilled_library
from tests.scene_graph.helpers import make_library, similarity

VIEWS = 3
ORBIT = OrbitConfig(n=VIEWS, width=128, height=96, radius=4.5)
"""Cameras well outside the tiny scene blob."""


@pytest.fixture(scope="module")
def data_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("bop")
    scene, _, proxies = make_library(root, ())
    libs = distilled_library(root)
    stage = root / "stage" / "scene.usda"
    # The library's meshes are its fields' own (marching cubes), so that the models match the renders.
    new_stage(stage, scene, libs, proxies={"scene": proxies["scene"]})
    add_instance(stage, "pouf", similarity(0.5, (1.2, -0.5, 0.0), 1.0))
    add_instance(stage, "pouf", similarity(1.5, (-1.2, 0.4, 0.0), 1.25))  # scaled: a model of its own
    add_instance(stage, "crate", similarity(-0.3, (0.3, 1.2, 0.2), 0.9, tilt=0.3))
    out = root / "data"
    cfg = GenerateConfig(format="bop", variants=2, cameras=ORBIT, executor=ExecutorConfig(kind="local", workers=2))
    report = generate(stage, out, cfg, progress=False)
    assert report.made == [0, 1] and not report.failed and len(report.notes) == 1
    return out


def gray(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im).astype(np.int64)


def load(path: Path) -> dict:
    return json.loads(path.read_text())


NEAR_MM = 1.0
"""Faces are clipped to this camera depth (mm) before they are drawn."""


def clip_to_near(polygon: np.ndarray, near: float) -> np.ndarray:
    """The part (m, 3) of a convex polygon (k, 3), camera mm, with z >= near (Sutherland-Hodgman)."""
    kept = []
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):  # a loop over edges
        if a[2] >= near:
            kept.append(a)
        if (a[2] >= near) != (b[2] >= near):
            kept.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    return np.asarray(kept).reshape(-1, 3)


def fill_triangle(out: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    """Set the pixels of ``out`` (h, w) whose centre ``(u + 0.5, v + 0.5)`` lies in the 2D triangle."""
    height, width = out.shape
    lo = np.maximum(np.floor(np.minimum(np.minimum(a, b), c) - 0.5), 0).astype(int)
    hi = np.minimum(np.ceil(np.maximum(np.maximum(a, b), c) - 0.5), [width - 1, height - 1]).astype(int)
    if (hi < lo).any():
        return
    u, v = np.meshgrid(np.arange(lo[0], hi[0] + 1) + 0.5, np.arange(lo[1], hi[1] + 1) + 0.5)
    p = np.stack([u, v], axis=-1)
    d = [(q[0] - p0[0]) * (p[..., 1] - p0[1]) - (q[1] - p0[1]) * (p[..., 0] - p0[0])
         for p0, q in ((a, b), (b, c), (c, a))]
    inside = ((d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0)) | ((d[0] <= 0) & (d[1] <= 0) & (d[2] <= 0))
    out[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] |= inside


def silhouette(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
               width: int, height: int) -> np.ndarray:
    """The model's silhouette: the pixels whose centre ``(u + 0.5, v + 0.5)`` lies in a face
    projected with ``K [R | t]``; a model that reaches behind the camera is drawn in front of it
    (its faces clipped to ``z >= NEAR_MM``)."""
    cam = vertices @ R.T + t
    out = np.zeros((height, width), dtype=bool)
    for tri in cam[faces]:  # a loop over faces, each over the pixels of its box
        poly = tri if (tri[:, 2] >= NEAR_MM).all() else clip_to_near(tri, NEAR_MM)
        if len(poly) < 3:
            continue
        uv = poly @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        for j in range(1, len(uv) - 1):  # the clipped polygon as a fan of triangles
            fill_triangle(out, uv[0], uv[j], uv[j + 1])
    return out


def test_models_are_millimetre_meshes_centred_with_their_diameters(data_set: Path) -> None:
    info = load(data_set / "bop" / "models" / "models_info.json")
    # The pouf at scales 1 and 1.25, the crate at 0.9.
    assert len(info) == 3
    for obj_id, entry in info.items():
        mesh = trimesh.load(data_set / "bop" / "models" / f"obj_{int(obj_id):06d}.ply", process=False)
        v = np.asarray(mesh.vertices, dtype=np.float64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        np.testing.assert_allclose(lo + hi, 0.0, atol=1e-3)  # origin at the 3D box's centre
        np.testing.assert_allclose([entry["size_x"], entry["size_y"], entry["size_z"]], hi - lo, rtol=1e-6)
        np.testing.assert_allclose([entry["min_x"], entry["min_y"], entry["min_z"]], lo, rtol=1e-6, atol=1e-6)
        far = max(float(np.linalg.norm(v - p, axis=1).max()) for p in v)  # every pair, by brute force
        assert entry["diameter"] == pytest.approx(far, rel=1e-6)
        assert 100.0 < entry["diameter"] < 3000.0  # millimetres, not metres
        assert len(mesh.vertex_normals) == len(v)


def test_each_scene_s_masks_and_counts_follow_the_instance_images(data_set: Path) -> None:
    for seed in (0, 1):
        scene = data_set / "bop" / "train" / f"{seed:06d}"
        variant = data_set / "variants" / f"{seed:06d}"
        cams, gts, infos = (load(scene / f"{n}.json") for n in ("scene_camera", "scene_gt", "scene_gt_info"))
        assert sorted(cams, key=int) == sorted(gts, key=int) == sorted(infos, key=int) == [str(k) for k in range(VIEWS)]
        for k in range(VIEWS):
            assert cams[str(k)]["depth_scale"] == 1.0
            assert np.array_equal(gray(scene / "depth" / f"{k:06d}.png"), gray(variant / f"depth_{k:04d}.png"))
            assert np.array_equal(gray(scene / "rgb" / f"{k:06d}.png"), gray(variant / f"rgb_{k:04d}.png"))
            ids, depth = gray(variant / f"instance_{k:04d}.png"), gray(scene / "depth" / f"{k:06d}.png")
            union = np.zeros_like(ids, dtype=bool)
            assert len(gts[str(k)]) == len(infos[str(k)]) == 3
            for g, inf in enumerate(infos[str(k)]):
                vis = gray(scene / "mask_visib" / f"{k:06d}_{g:06d}.png") > 0
                full = gray(scene / "mask" / f"{k:06d}_{g:06d}.png") > 0
                assert not (vis & union).any() and not (vis & ~full).any()
                union |= vis
                if vis.any():  # one instance's pixels in the instance image
                    assert len(np.unique(ids[vis])) == 1 and np.array_equal(vis, ids == ids[vis][0])
                assert inf["px_count_visib"] == vis.sum() and inf["px_count_all"] == full.sum()
                assert inf["px_count_valid"] == (full & (depth > 0)).sum()
                assert inf["visib_fract"] == pytest.approx(vis.sum() / max(full.sum(), 1))
                if full.any():
                    rows, cols = np.flatnonzero(full.any(axis=1)), np.flatnonzero(full.any(axis=0))
                    assert inf["bbox_obj"] == [cols[0], rows[0], cols[-1] - cols[0] + 1, rows[-1] - rows[0] + 1]
            assert np.array_equal(union, ids > 0)


def test_the_poses_project_the_models_onto_the_whole_masks(data_set: Path) -> None:
    models = data_set / "bop" / "models"
    checked = 0
    for seed in (0, 1):
        scene = data_set / "bop" / "train" / f"{seed:06d}"
        cams, gts = load(scene / "scene_camera.json"), load(scene / "scene_gt.json")
        for k in range(VIEWS):
            K = np.asarray(cams[str(k)]["cam_K"], dtype=np.float64).reshape(3, 3)
            for g, gt in enumerate(gts[str(k)]):
                full = gray(scene / "mask" / f"{k:06d}_{g:06d}.png") > 0
                if full.sum() < 30:
                    continue
                mesh = trimesh.load(models / f"obj_{gt['obj_id']:06d}.ply", process=False)
                R = np.asarray(gt["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)  # rigid, as BOP has it
                drawn = silhouette(np.asarray(mesh.vertices), np.asarray(mesh.faces), K, R,
                                   np.asarray(gt["cam_t_m2c"], dtype=np.float64), full.shape[1], full.shape[0])
                iou = (drawn & full).sum() / (drawn | full).sum()
                assert iou >= 0.9, f"seed {seed} view {k} gt {g} (obj {gt['obj_id']}): IoU {iou:.3f}"
                checked += 1
    assert checked >= 6, "too few objects in view to test anything"


def test_a_variant_whose_bop_scene_is_gone_is_made_again(data_set: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "data"
    shutil.copytree(data_set, copy, symlinks=True)
    scene = copy / "bop" / "train" / f"{1:06d}"
    before = {p.relative_to(scene): p.read_bytes() for p in scene.rglob("*") if p.is_file()}
    shutil.rmtree(scene)
    stage = load(copy / "generation.json")["source_stage"]  # the stage the fixture made
    cfg = GenerateConfig(format="bop", variants=2, cameras=ORBIT, executor=ExecutorConfig(kind="local", workers=1))
    report = generate(stage, copy, cfg, progress=False)
    assert report.made == [1] and report.skipped == [0] and not report.failed
    after = {p.relative_to(scene): p.read_bytes() for p in scene.rglob("*") if p.is_file()}
    assert sorted(after) == sorted(before)
    for rel in ("scene_gt.json", "scene_camera.json"):  # the same variant again: the same poses
        assert load(scene / rel) == json.loads(before[Path(rel)])


def test_a_model_is_the_library_objects_source_mesh_when_it_has_one() -> None:
    from types import SimpleNamespace

    from regnf.datasets.data_set_formats import model_mesh
    from regnf.meshes.source_mesh import SourceMesh
    from regnf.scene_graph import ProxyMesh

    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    colours = np.random.default_rng(0).random((len(box.faces), 3)).astype(np.float32)
    proxy = ProxyMesh(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), None)
    src = SourceMesh(np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.int32), np.ones(3, np.float32),
                     colours)
    model = model_mesh(SimpleNamespace(source_mesh=src, proxy=proxy))
    # The same triangles, each face's corners in its own colour.
    np.testing.assert_allclose(model.vertices[model.faces], box.vertices[box.faces], atol=1e-6)
    rgb = np.asarray(model.visual.vertex_colors)[:, :3].reshape(-1, 3, 3)
    np.testing.assert_array_equal(rgb, np.repeat(np.round(255 * colours).astype(np.uint8)[:, None], 3, axis=1))
    # Without one: the field's mesh as the stage holds it.
    plain = model_mesh(SimpleNamespace(source_mesh=None, proxy=proxy))
    np.testing.assert_array_equal(plain.vertices, proxy.points)
