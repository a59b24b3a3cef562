"""Meshes that are not what ``regnf distill`` expects: a soup of random triangles, faces at NaN
vertices, an OBJ whose material file is a FIFO or lies outside its folder, a mesh in millimetres.

A mesh that cannot be distilled is refused with one line naming the file, exit status 1, and
nothing on disk changed; one that can is distilled with one warning line saying what was
skipped, dropped or is implausible. Nothing blocks: a command that has not returned after
:data:`BLOCKED_S` fails the test (a FIFO is released so that the test itself never hangs).
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from regnf.io.checkpoint import read_header
from regnf.meshes.mesh_reading import load_mesh_file
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails, run_cli

BLOCKED_S = 60.0
"""Seconds after which a command that has not returned is taken to be blocked."""
SOUP_S = 10.0
"""The soup of random triangles is refused within this many seconds (it once ran for minutes)."""
STEPS = ["--distillation.steps", "1"]
"""The mesh checks and targets are what these tests exercise, not the training."""


def box_obj(mtllib: str) -> str:
    """The text of an OBJ of a 0.4 x 0.3 x 0.2 m box naming material file ``mtllib``."""
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    return (f"mtllib {mtllib}\nusemtl red\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in box.vertices)
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces))


def run_within(capsys: pytest.CaptureFixture[str], args: list[str], fifo: Path | None = None) -> tuple[int, str]:
    """``run_cli`` in a thread; fail if it has not returned after :data:`BLOCKED_S` (then
    ``fifo``, if given, is opened for writing so that a reader blocked on it returns)."""
    outcome: dict[str, object] = {}

    def attempt() -> None:
        try:
            outcome["result"] = run_cli(capsys, args)
        except BaseException as exc:  # noqa: BLE001 (re-raised in the test's thread)
            outcome["error"] = exc

    thread = threading.Thread(target=attempt, daemon=True)
    thread.start()
    thread.join(BLOCKED_S)
    if thread.is_alive():
        if fifo is not None:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail(f"regnf {' '.join(args[:2])} still runs after {BLOCKED_S} s: it blocked")
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    return outcome["result"]  # type: ignore[return-value]


def warnings_of(err: str) -> list[str]:
    """The warning lines of a command's stderr, without the ``warning: `` prefix."""
    return [line.removeprefix("warning: ") for line in err.splitlines() if line.startswith("warning: ")]


@pytest.fixture()
def work(tmp_path: Path) -> Path:
    """The folder of the cache and outputs (snapshotted; meshes with special files live beside it)."""
    (tmp_path / "work").mkdir()
    return tmp_path / "work"


def test_an_obj_whose_material_file_is_a_fifo_is_distilled_without_it(tmp_path, work, capsys) -> None:
    folder = tmp_path / "fifo"
    folder.mkdir()
    (folder / "box.obj").write_text(box_obj("pipe.mtl"))
    os.mkfifo(folder / "pipe.mtl")
    status, err = run_within(capsys, ["distill", "--mesh", str(folder / "box.obj"), *STEPS,
                                      "--cache-dir", str(work / "cache")], fifo=folder / "pipe.mtl")
    assert status == 0, err
    assert warnings_of(err) == [(f"{folder / 'box.obj'}: skipped the files it names that are not regular files "
                                "inside its folder: pipe.mtl is not a file (a FIFO)")]
    assert sorted(p.name for p in folder.iterdir()) == ["box.obj", "pipe.mtl"]


def test_a_material_file_outside_the_mesh_folder_is_not_read(tmp_path, work, capsys) -> None:
    """Through a symlink that leaves the folder, or by an absolute path: skipped, said once."""
    outside = tmp_path / "secret.mtl"
    outside.write_text("newmtl red\nKd 1 0 0\n")
    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / "link.mtl").symlink_to(outside)
    (folder / "linked.obj").write_text(box_obj("link.mtl"))
    (folder / "absolute.obj").write_text(box_obj(str(outside)))
    (folder / "inside.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (folder / "inside.obj").write_text(box_obj("inside.mtl"))
    for name, why in (("linked.obj", "link.mtl is outside the mesh's folder"),
                      ("absolute.obj", f"{outside} is outside the mesh's folder")):
        read = load_mesh_file(folder / name)
        assert read.warnings == [(f"{folder / name}: skipped the files it names that are not regular files "
                                 f"inside its folder: {why}")]
        assert read.mesh.visual.kind is None  # no material was read
    # The control: a material file inside the folder is read, without a word.
    inside = load_mesh_file(folder / "inside.obj")
    assert inside.warnings == [] and inside.mesh.visual.kind is not None
    before = snapshot(folder)
    status, err = run_within(capsys, ["distill", "--mesh", str(folder / "linked.obj"), *STEPS,
                                      "--cache-dir", str(work / "cache")])
    assert status == 0 and len(warnings_of(err)) == 1, err
    assert changes(before, snapshot(folder)) == []


def nan_box(path: Path, bad: int) -> None:
    """A box OBJ with ``bad`` more faces, each with a NaN or infinite vertex."""
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    v = np.concatenate([box.vertices, [[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0]]])
    extra = np.array([[8, 0, 1], [9, 2, 3], [8, 9, 4]])[:bad]
    text = "".join(f"v {x} {y} {z}\n" for x, y, z in v)
    text += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in np.concatenate([box.faces, extra]))
    path.write_text(text)


def test_faces_at_non_finite_vertices_are_dropped_and_counted(work, capsys) -> None:
    mesh = work / "nan.obj"
    nan_box(mesh, bad=3)
    status, err = run_within(capsys, ["distill", "--mesh", str(mesh), *STEPS, "--cache-dir", str(work / "cache")])
    assert status == 0, err
    assert warnings_of(err) == [f"{mesh}: dropped 3 faces with non-finite vertices"]


def test_a_mesh_whose_every_face_has_a_nan_vertex_is_refused(work, capsys) -> None:
    mesh = work / "allnan.obj"
    mesh.write_text("v nan 0 0\nv 0 nan 0\nv 0 0 inf\nv 1 1 1\nf 1 2 3\nf 1 2 4\n")
    before = snapshot(work)
    assert_fails(capsys, ["distill", "--mesh", str(mesh), *STEPS, "--cache-dir", str(work / "cache")],
                 rf"^regnf distill: {mesh}: each of its 2 faces has a non-finite \(NaN or inf\) vertex; "
                 "nothing is left to distil$")
    assert changes(before, snapshot(work)) == []


def test_a_soup_of_random_triangles_is_refused_in_seconds(work, capsys) -> None:
    """150 random triangles (a 7 KB file) once ran for minutes and gigabytes."""
    mesh = work / "soup.ply"
    v = np.random.default_rng(0).random((450, 3))
    trimesh.Trimesh(v, np.arange(450).reshape(-1, 3), process=False).export(mesh)
    run_cli(capsys, ["distill", "--mesh", str(work / "missing.ply")])  # the imports, untimed
    before = snapshot(work)
    t0 = time.perf_counter()
    assert_fails(capsys, ["distill", "--mesh", str(mesh), "--cache-dir", str(work / "cache")],
                 rf"^regnf distill: {mesh}: its faces bound no solid: rays from \d+ % of the points in its box "
                 r"disagree on whether they are inside, and almost none are inside for every ray "
                 r"\(a soup of open triangles\?\)$")
    assert time.perf_counter() - t0 < SOUP_S
    assert changes(before, snapshot(work)) == []


def box_file(path: Path, size: float) -> Path:
    """A cube of side ``size`` (in the file's units)."""
    trimesh.creation.box(extents=(size, 0.75 * size, 0.5 * size)).export(path)
    return path


def test_a_mesh_in_millimetres_is_said_and_converted_with_units(work, capsys) -> None:
    mesh = box_file(work / "chair_mm.ply", 400.0)
    args = ["distill", "--mesh", str(mesh), *STEPS, "--cache-dir", str(work / "cache")]
    status, err = run_within(capsys, [*args, "--out", str(work / "m.safetensors")])
    assert status == 0, err
    assert warnings_of(err) == [f"{mesh}: the mesh is 400 m across; if its unit is not metres, pass --units mm or cm"]
    status, err = run_within(capsys, [*args, "--units", "mm", "--out", str(work / "mm.safetensors")])
    assert status == 0 and warnings_of(err) == [], err
    header = read_header(work / "mm.safetensors")
    provenance = header["provenance"]
    assert provenance["units"] == "mm" and provenance["metres_per_unit"] == 0.001
    assert provenance["train_config"]["scale"] == 0.001
    # The field frame's unit: half the largest extent (0.4 m) times the margin 1.15.
    assert np.array(header["to_world"])[0, 0] == pytest.approx(0.2 * 1.15)
    # The same mesh at --scale 0.001 is the same field; a small mesh is said too.
    status, err = run_within(capsys, [*args, "--scale", "0.001", "--out", str(work / "s.safetensors")])
    assert status == 0 and warnings_of(err) == [], err
    tiny = box_file(work / "tiny.ply", 0.004)
    status, err = run_within(capsys, ["distill", "--mesh", str(tiny), *STEPS, "--cache-dir", str(work / "cache")])
    assert status == 0, err
    assert warnings_of(err) == [(f"{tiny}: the mesh is 4 mm across; if its unit is not metres, pass --scale "
                                "(metres per unit of the file)")]


@pytest.mark.parametrize(("extra", "pattern"), [
    (["--units", "mm", "--scale", "0.001"], r"^regnf distill: --units mm and --scale 0.001: give one of them$"),
    (["--scale", "0"], r"^regnf distill: --scale 0.0: must be a positive number of metres per unit$"),
    (["--scale", "nan"], r"^regnf distill: --scale nan: must be a positive number of metres per unit$"),
])
def test_contradictory_or_impossible_units_are_refused(work, capsys, extra, pattern) -> None:
    mesh = box_file(work / "box.ply", 0.4)
    before = snapshot(work)
    assert_fails(capsys, ["distill", "--mesh", str(mesh), *STEPS, "--cache-dir", str(work / "cache"), *extra], pattern)
    assert changes(before, snapshot(work)) == []
