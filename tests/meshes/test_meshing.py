"""Marching-cubes meshes of analytic fields against closed-form geometry."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from regnf.fields.analytic import Box, Sphere
from regnf.fields.similarity import similarity_matrix
from regnf.meshes.meshing import extract_mesh, grid_shape, save_mesh

R0, C0 = 0.6, np.array([0.1, -0.2, 0.05])
COLOR = (0.2, 0.4, 0.6)
RES = 64


@pytest.fixture(scope="module")
def sphere() -> Sphere:
    to_world = similarity_matrix(Rotation.random(random_state=0).as_matrix(), [1.0, 2.0, 3.0], 2.5)
    return Sphere(R0, C0, color=COLOR, to_world=to_world)


@pytest.fixture(scope="module")
def mesh(sphere: Sphere) -> trimesh.Trimesh:
    return extract_mesh(sphere, resolution=RES)


def test_sphere_mesh_geometry(sphere: Sphere, mesh: trimesh.Trimesh) -> None:
    voxel = float((sphere.bounds[1] - sphere.bounds[0]).max()) / RES
    dist = np.linalg.norm(mesh.vertices - C0, axis=1)
    assert len(mesh.vertices) > 1000
    assert np.abs(dist - R0).max() <= 0.5 * voxel
    assert mesh.is_watertight
    true_volume = 4.0 / 3.0 * math.pi * R0**3
    assert abs(mesh.volume - true_volume) / true_volume < 0.02  # signed: > 0 means outward


def test_faces_point_outward(mesh: trimesh.Trimesh) -> None:
    radial = mesh.triangles_center - C0
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals, radial) > 0)
    assert np.all(np.einsum("ij,ij->i", mesh.vertex_normals, mesh.vertices - C0) > 0)


def test_vertex_colors(mesh: trimesh.Trimesh) -> None:
    vc = mesh.visual.vertex_colors
    assert vc.dtype == np.uint8 and vc.shape == (len(mesh.vertices), 4)
    expect = np.round(np.array(COLOR) * 255).astype(np.uint8)
    assert np.all(vc[:, :3] == expect) and np.all(vc[:, 3] == 255)
    plain = extract_mesh(Sphere(0.5), resolution=16, with_color=False)
    assert plain.visual.kind is None  # no colours were set


def test_in_world_applies_to_world(sphere: Sphere, mesh: trimesh.Trimesh) -> None:
    world = extract_mesh(sphere, resolution=RES, in_world=True)
    M = sphere.to_world.numpy()
    np.testing.assert_allclose(world.vertices, mesh.vertices @ M[:3, :3].T + M[:3, 3], atol=1e-9)
    centre_w = M[:3, :3] @ C0 + M[:3, 3]
    r_w = 2.5 * R0
    assert abs(np.linalg.norm(world.vertices - centre_w, axis=1).mean() - r_w) < 0.01 * r_w
    assert world.volume > 0


@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_save_and_reload(tmp_path: Path, mesh: trimesh.Trimesh, suffix: str) -> None:
    path = save_mesh(mesh, tmp_path / f"sub/sphere{suffix}")
    assert path.exists()
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temp file left over
    back = trimesh.load(path, force="mesh")
    assert len(back.faces) == len(mesh.faces)
    np.testing.assert_allclose(back.bounds, mesh.bounds, atol=1e-5)
    assert abs(back.volume - mesh.volume) < 1e-4 * mesh.volume
    np.testing.assert_array_equal(
        np.unique(back.visual.vertex_colors, axis=0), np.unique(mesh.visual.vertex_colors, axis=0)
    )


def test_save_rejects_unknown_suffix(tmp_path: Path, mesh: trimesh.Trimesh) -> None:
    with pytest.raises(ValueError, match=".ply or .glb"):
        save_mesh(mesh, tmp_path / "sphere.obj")
    assert list(tmp_path.iterdir()) == []


def test_empty_grid_raises() -> None:
    f = Sphere(0.5)
    with pytest.raises(ValueError, match="no surface"):
        extract_mesh(f, resolution=8, bounds=np.array([[2.0, 2.0, 2.0], [3.0, 3.0, 3.0]]))
    with pytest.raises(ValueError, match="no surface"):  # entirely inside
        extract_mesh(f, resolution=8, bounds=np.array([[-0.1] * 3, [0.1] * 3]))
    with pytest.raises(ValueError, match="bounds"):
        extract_mesh(f, resolution=8, bounds=np.array([[0.0] * 3, [0.0] * 3]))
    with pytest.raises(ValueError, match="resolution"):
        extract_mesh(f, resolution=1)


def test_anisotropic_grid() -> None:
    cells, spacing = grid_shape(np.array([[0.0, 0.0, 0.0], [2.0, 1.0, 0.5]]), 40)
    assert cells.tolist() == [40, 20, 10]
    np.testing.assert_allclose(spacing, 0.05)
    box = Box((0.8, 0.4, 0.2), (0.0, 0.0, 0.3), color=(1.0, 0.0, 0.0))
    m = extract_mesh(box, resolution=48)
    np.testing.assert_allclose(m.bounds, [[-0.8, -0.4, 0.1], [0.8, 0.4, 0.5]], atol=0.02)
    assert abs(m.volume - 1.6 * 0.8 * 0.4) / (1.6 * 0.8 * 0.4) < 0.03
    assert m.volume > 0


def test_chunk_and_device_explicit(sphere: Sphere) -> None:
    small = extract_mesh(sphere, resolution=16, chunk=500, device=torch.device("cpu"))
    big = extract_mesh(sphere, resolution=16)
    np.testing.assert_allclose(small.vertices, big.vertices)
    np.testing.assert_array_equal(small.faces, big.faces)


def test_grid_chunks_side_by_side_are_the_bits_of_one_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    # A network (its batched evaluation is where threads could change bits): chunks on two
    # threads give the grid of one after another on one thread, each in its own place.
    import regnf.meshes.meshing as M
    from regnf.core.threads import one_thread
    from tests.io.test_checkpoint import make_field

    field = make_field()
    bounds = field.bounds.double().numpy()
    cells, _ = grid_shape(bounds, 20)
    two = M.sample_grid(field, bounds, cells, chunk=700)
    monkeypatch.setattr(M, "usable_cores", lambda: 1)
    with one_thread():
        one = M.sample_grid(field, bounds, cells, chunk=700)
    np.testing.assert_array_equal(two, one)
    # And each node holds its own point's value.
    ijk = np.array([[0, 0, 0], [3, 7, 2], [20, 13, 15]])
    ijk = np.minimum(ijk, cells)
    pts = bounds[0] + ijk * (bounds[1] - bounds[0]) / cells
    with torch.no_grad():
        want = field.sdf(torch.as_tensor(pts, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(two[tuple(ijk.T)], want, atol=1e-6)
