"""The distillation cache: a key that sees vertex colours, and one distillation for two processes."""

from __future__ import annotations

import hashlib
import multiprocessing
import time
from pathlib import Path

import numpy as np
import trimesh

from regnf.core.file_lock import file_lock
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.io.checkpoint import load_field
from regnf.meshes.source_mesh import read_source_mesh, source_mesh_file
from regnf.render.evaluation import world_to_field
from regnf.synthetic import cache as cache_module
from regnf.synthetic.cache import Cache, mesh_digest
from regnf.training.distill import DistillConfig

TINY = NeuralSDFConfig(levels=3, features_per_level=2, base_resolution=8, finest_resolution=16,
                       hidden_dim=16, color_hidden_dim=16)
QUICK = DistillConfig(steps=60, batch=512, pool_surface=3000, architecture=TINY)
"""Enough steps for a field's colour to take its mesh's hue."""


def coloured_box(rgb: tuple[int, int, int]) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    box.visual.vertex_colors = np.tile([*rgb, 255], (len(box.vertices), 1)).astype(np.uint8)
    return box


def test_vertex_colours_are_part_of_the_key_and_of_the_field(tmp_path: Path) -> None:
    """The same mesh re-exported with blue vertex colours is another field, and a blue one."""
    cache = Cache(tmp_path, progress=False)
    fields = {}
    for name, rgb in (("red", (230, 20, 20)), ("blue", (20, 20, 230))):
        path = tmp_path / f"{name}.ply"
        coloured_box(rgb).export(path)
        mesh = trimesh.load(path, force="mesh")
        assert mesh.visual.kind == "vertex"
        fields[name] = cache.distilled_field(mesh, FieldInfo(name="box"), QUICK)
    assert fields["red"] != fields["blue"]
    # Each keeps the mesh it was distilled from, with its colours, for tools that render meshes;
    # one lost is made again when the field is reused.
    for name, rgb in (("red", (230, 20, 20)), ("blue", (20, 20, 230))):
        kept = read_source_mesh(fields[name])
        np.testing.assert_allclose(kept.face_colors, np.tile(np.asarray(rgb) / 255.0, (12, 1)), atol=1e-6)
    source_mesh_file(fields["red"]).unlink()
    mesh = trimesh.load(tmp_path / "red.ply", force="mesh")
    assert cache.distilled_field(mesh, FieldInfo(name="box"), QUICK) == fields["red"]
    np.testing.assert_allclose(read_source_mesh(fields["red"]).points, mesh.vertices, atol=1e-6)
    assert fields["red"].read_bytes() != fields["blue"].read_bytes()
    pts, _ = trimesh.sample.sample_surface(coloured_box((0, 0, 0)), 2000, seed=1)
    for name, channel in (("red", 0), ("blue", 2)):
        field = load_field(fields[name])
        rgb = field.color(world_to_field(field, pts)).detach().numpy().mean(axis=0)
        assert rgb[channel] > rgb[2 - channel] + 0.1, (name, rgb)  # the hue, not yet the exact colour
    # Face colours keep the key they had: the bytes of the face colours as stored.
    faces = trimesh.creation.box()
    faces.visual.face_colors = [10, 200, 30, 255]
    old = hashlib.sha256(faces.vertices.tobytes() + faces.faces.tobytes() + faces.visual.face_colors.tobytes())
    assert mesh_digest(faces) == old.hexdigest()


def _distil_in_child(root: str, vertices: np.ndarray, faces: np.ndarray, marks: str) -> None:
    """Distil the mesh into the cache at ``root``, leaving a mark when targets are ready and
    another if it trains."""

    def prepared(*args, **kwargs):
        out = targets(*args, **kwargs)
        Path(marks, "prepared").touch()
        return out

    def trained(*args, **kwargs):
        Path(marks, "trained").touch()
        return train(*args, **kwargs)

    targets, train = cache_module.distillation_targets, cache_module.distill_mesh
    cache_module.distillation_targets, cache_module.distill_mesh = prepared, trained
    path = Cache(Path(root), progress=False).distilled_field(
        trimesh.Trimesh(vertices, faces, process=False), FieldInfo(name="box"), QUICK)
    Path(marks, "result").write_text(str(path))


def test_a_second_distillation_waits_for_the_first_and_reuses_its_field(tmp_path: Path) -> None:
    """This process holds the entry's lock (as a first distillation would) while a second
    process prepares the same mesh; that one waits, then reuses the entry made meanwhile."""
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    cache = Cache(tmp_path / "cache", progress=False)
    entry, _ = cache.distilled_entry(box, FieldInfo(name="box"), QUICK)
    entry.parent.mkdir(parents=True)
    marks = tmp_path / "marks"
    marks.mkdir()
    child = multiprocessing.get_context("spawn").Process(
        target=_distil_in_child, args=(str(cache.root), box.vertices, box.faces, str(marks)))
    with file_lock(entry.parent / f".{entry.name}.lock", "the cache entry"):
        child.start()
        deadline = time.monotonic() + 120
        while not (marks / "prepared").exists() and child.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (marks / "prepared").exists(), "the second process never got to the lock"
        time.sleep(0.5)
        assert child.is_alive() and not entry.exists()  # waiting on the lock
        made = cache.distilled_field(box, FieldInfo(name="box"), QUICK)  # the lock nests here
    child.join(120)
    assert child.exitcode == 0
    assert made == entry and (marks / "result").read_text() == str(entry)
    assert not (marks / "trained").exists()  # reused, not trained again
