"""The source mesh a distilled field keeps: its frame, its colours or texture, and damaged files."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from safetensors.numpy import save_file

from regnf.meshes.source_mesh import (
    SourceMeshError,
    keep_source_mesh,
    load_source_mesh,
    read_source_mesh,
    source_mesh_file,
)


def textured_box() -> tuple[trimesh.Trimesh, np.ndarray]:
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    texture = np.random.default_rng(0).integers(0, 256, (6, 10, 3), dtype=np.uint8)
    uv = np.random.default_rng(1).random((len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture))
    return box, texture


def test_the_mesh_is_kept_in_the_fields_frame_with_its_units_and_up_axis(tmp_path: Path) -> None:
    mesh = trimesh.creation.box(extents=(400.0, 300.0, 200.0))  # millimetres, +Y up
    mesh.visual.face_colors = np.tile([200, 10, 20, 255], (len(mesh.faces), 1))
    ckpt = tmp_path / "box.safetensors"
    path = keep_source_mesh(mesh, ckpt, scale=0.001, up="y")
    assert path == source_mesh_file(ckpt) == tmp_path / "box.source-mesh.safetensors"
    got = read_source_mesh(ckpt)
    # A Y-up file turns (x, y, z) -> (x, -z, y); millimetres to metres.
    v = np.asarray(mesh.vertices) * 0.001
    np.testing.assert_allclose(got.points, np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1), atol=1e-7)
    np.testing.assert_array_equal(got.faces, mesh.faces)
    np.testing.assert_allclose(got.face_colors, np.tile([200 / 255, 10 / 255, 20 / 255], (12, 1)), atol=1e-7)
    assert got.uv is None and got.texture is None


def test_a_texture_is_kept_as_png_with_its_coordinates(tmp_path: Path) -> None:
    box, texture = textured_box()
    keep_source_mesh(box, tmp_path / "t.safetensors")
    got = read_source_mesh(tmp_path / "t.safetensors")
    np.testing.assert_allclose(got.uv, np.asarray(box.visual.uv), atol=1e-7)
    with Image.open(io.BytesIO(got.texture)) as im:
        np.testing.assert_array_equal(np.asarray(im.convert("RGB")), texture)
    assert got.face_colors is None


def test_a_mesh_without_colours_keeps_the_grey_distillation_gives_it(tmp_path: Path) -> None:
    keep_source_mesh(trimesh.creation.icosphere(), tmp_path / "s.safetensors")
    got = read_source_mesh(tmp_path / "s.safetensors")
    np.testing.assert_allclose(got.base_color, [0.7, 0.7, 0.7], atol=1e-7)
    assert got.face_colors is None and got.texture is None


def test_no_file_is_none_and_a_damaged_one_is_named(tmp_path: Path) -> None:
    assert read_source_mesh(tmp_path / "none.safetensors") is None
    bad = tmp_path / "bad.source-mesh.safetensors"
    bad.write_bytes(b"\x00" * 40)
    with pytest.raises(SourceMeshError, match="bad.source-mesh.safetensors: not a source mesh file"):
        load_source_mesh(bad)
    # Written by hand, not by regnf: a face index past the last point, and a texture that is no PNG.
    pts = np.zeros((3, 3), np.float32)
    grey = np.full(3, 0.5, np.float32)
    save_file({"points": pts, "faces": np.array([[0, 1, 3]], np.int32), "base_color": grey}, str(bad))
    with pytest.raises(SourceMeshError, match="face indices out of range"):
        load_source_mesh(bad)
    save_file({"points": pts, "faces": np.array([[0, 1, 2]], np.int32), "base_color": grey,
               "uv": np.zeros((3, 2), np.float32), "texture": np.frombuffer(b"GIF89a....", np.uint8).copy()}, str(bad))
    with pytest.raises(SourceMeshError, match="not a readable PNG"):
        load_source_mesh(bad)
    save_file({"points": pts, "faces": np.array([[0, 1, 2]], np.int32), "base_color": grey,
               "uv": np.zeros((3, 2), np.float32)}, str(bad))
    with pytest.raises(SourceMeshError, match="uv and texture go together"):
        load_source_mesh(bad)
