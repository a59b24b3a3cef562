"""Meshes of fields far from the origin (geo-referenced scans sit at 1e5 m; 1e9 m is the extreme):
``regnf mesh`` keeps every vertex where the float64 ``to_world`` puts it.

float32 rounds a coordinate of 1e5 m to 4 mm and one of 1e9 m to 64 m. The truths are
independent of the export: an analytic sphere's exact surface, and the field-frame mesh mapped
by ``to_world`` in float64 with numpy; the files are read back by trimesh and by a PLY parser
written here with numpy (not regnf's writer's code).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from regnf.fields.analytic import Sphere
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDF
from regnf.io.checkpoint import load_field, save_field
from regnf.meshes.mesh_writing import written_rounding
from regnf.meshes.meshing import extract_mesh, save_mesh
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import run_cli
from tests.scene_graph.helpers import TINY

RADIUS = 0.5
"""Metres."""
SURFACE_ATOL = 1e-3
"""Sub-millimetre: marching cubes at 32 cells on a 0.5 m sphere is within 0.3 mm of the surface."""
MAPPED_ATOL = 1e-6
"""Metres between a written vertex and its float64 truth (float64 resolves 1.2e-7 m at 1e9 m)."""
PLY_TYPES = {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4"}


def read_ply_vertices(path: Path) -> np.ndarray:
    """(N, 3) float64 vertices of a binary little-endian PLY, parsed from its header with numpy alone."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[1] == "format binary_little_endian 1.0", lines[1]
    count, fields, in_vertex = 0, [], False
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count, in_vertex = int(words[2]), True
        elif words[:1] == ["element"]:
            in_vertex = False
        elif words[:1] == ["property"] and in_vertex:
            fields.append((words[2], PLY_TYPES[words[1]]))
    vertex = np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=end)
    return np.stack([vertex[a].astype(np.float64) for a in "xyz"], axis=1)


def translation(offset: float) -> np.ndarray:
    """(4, 4) a translation by ``offset`` metres, different on each axis."""
    M = np.eye(4)
    M[:3, 3] = [offset, -0.5 * offset, 0.25 * offset + 0.123456]
    return M


@pytest.mark.parametrize("offset", [1e5, 1e9])
@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_a_sphere_far_from_the_origin_is_written_where_it_is(tmp_path: Path, offset: float, suffix: str) -> None:
    M = translation(offset)
    sphere = Sphere(RADIUS, to_world=M)
    local = extract_mesh(sphere, resolution=32, with_color=False)
    world = extract_mesh(sphere, resolution=32, with_color=False, in_world=True)
    path = save_mesh(world, tmp_path / f"sphere{suffix}")
    back = trimesh.load(path, force="mesh")
    readers = [back.vertices] + ([read_ply_vertices(path)] if suffix == ".ply" else [])
    truth = local.vertices + M[:3, 3]  # float64, by numpy
    for vertices in readers:
        assert len(vertices) == len(local.vertices)
        np.testing.assert_allclose(vertices, truth, rtol=0, atol=MAPPED_ATOL)
        off_surface = np.abs(np.linalg.norm(vertices - M[:3, 3], axis=1) - RADIUS)
        assert off_surface.max() < SURFACE_ATOL, off_surface.max()
    assert written_rounding(world, suffix[1:]) < MAPPED_ATOL


def _checkpoint(folder: Path, to_world: np.ndarray) -> Path:
    """A tiny neural field (a blob about 1 field unit across) placed by ``to_world``."""
    torch.manual_seed(0)
    field = NeuralSDF(TINY, to_world=torch.as_tensor(to_world, dtype=torch.float64),
                      info=FieldInfo(label="scan", name="far"))
    return save_field(field, folder / "far.safetensors")


def test_regnf_mesh_keeps_a_field_at_1e9_m_to_the_micrometre(tmp_path: Path, capsys) -> None:
    M = translation(1e9)
    ckpt = _checkpoint(tmp_path, M)
    out = tmp_path / "far.ply"
    status, err = run_cli(capsys, ["mesh", "--field", str(ckpt), "--out", str(out), "--resolution", "16"])
    assert status == 0, err
    assert "warning" not in err
    local = extract_mesh(load_field(ckpt), resolution=16, with_color=False)
    truth = local.vertices @ M[:3, :3].T + M[:3, 3]
    vertices = read_ply_vertices(out)
    assert len(vertices) == len(truth) > 100
    np.testing.assert_allclose(vertices, truth, rtol=0, atol=MAPPED_ATOL)
    # float32 would put every vertex on a 64 m lattice: the whole mesh one point.
    assert np.ptp(vertices, axis=0).min() > 0.1


def test_a_glb_that_float32_cannot_hold_to_a_millimetre_warns(tmp_path: Path, capsys) -> None:
    M = np.diag([1e5, 1e5, 1e5, 1.0])  # a blob 100 km across: float32 rounds its vertices by millimetres
    ckpt = _checkpoint(tmp_path, M)
    before = snapshot(tmp_path)
    status, err = run_cli(capsys, ["mesh", "--field", str(ckpt), "--out", str(tmp_path / "big.glb"),
                                   "--resolution", "16"])
    assert status == 0, err
    warning = next(line for line in err.splitlines() if "warning" in line)
    assert f"{tmp_path / 'big.glb'} holds its vertices as float32, which moves them by up to" in warning
    assert "write a .ply (float64)" in warning
    assert changes(before, snapshot(tmp_path)) == ["added big.glb"]
    status, err = run_cli(capsys, ["mesh", "--field", str(ckpt), "--out", str(tmp_path / "big.ply"),
                                   "--resolution", "16"])
    assert status == 0 and "warning" not in err, err
