"""The command line as a hostile user drives it: every bad input is one line and a documented
exit status, checked before any long work, with nothing written.

Each test runs ``regnf`` in-process (the same ``main`` as the console script) and asserts the
status, the one error line (naming the file or option) and, where it matters, that the work
itself never started (the loader or the registration is replaced by a function that fails
the test if it is reached).
"""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

import regnf.registration.pipeline as register_module
from regnf.cli import commands_fields, commands_registration
from regnf.cli.app import EXIT_BAD_INPUT, EXIT_INTERNAL, main
from regnf.compositor.composite_field import MAX_COMPONENTS, CompositeField
from regnf.compositor.placement import PlacedObject
from regnf.compositor.render_folder import MAX_PIXELS
from regnf.fields.analytic import Sphere
from tests.adversarial.disk import changes, snapshot
from tests.adversarial.mounts import tmpfs
from tests.cli.cli_helpers import assert_fails, run_cli
from tests.scene_graph.helpers import checkpoint


def _never(*args: object, **kwargs: object) -> None:
    raise AssertionError("the command started its work before checking its inputs")


@pytest.fixture()
def tiny(tmp_path: Path) -> Path:
    """A valid tiny checkpoint."""
    return checkpoint(tmp_path, "c", "chair")


@pytest.fixture()
def corrupt(tmp_path: Path) -> Path:
    path = tmp_path / "corrupt.safetensors"
    path.write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{not json")
    return path


@pytest.fixture()
def good_box(tmp_path: Path) -> Path:
    path = tmp_path / "box.json"
    path.write_text(json.dumps({"center": [0, 0, 0.4], "size": [0.5, 0.5, 0.8], "yaw": 0.3}))
    return path


@pytest.fixture()
def read_only_dir(tmp_path: Path) -> Iterator[Path]:
    """A folder nobody may write: mode 0555, or for root (whom modes do not stop) a read-only mount."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    with tmpfs(folder, "ro,size=64k"):
        yield folder


def test_a_corrupt_checkpoint_is_one_line_for_mesh_and_register(tmp_path, corrupt, good_box, capsys) -> None:
    before = snapshot(tmp_path)
    assert_fails(capsys, ["mesh", "--field", str(corrupt), "--out", str(tmp_path / "m.ply"),
                          "--resolution", "16"], rf"^regnf mesh: {corrupt}: ")
    assert_fails(capsys, ["register", "--scene", str(corrupt), "--library", str(corrupt), "--box", str(good_box),
                          "--out", str(tmp_path / "r.json")], rf"^regnf register: {corrupt}: ")
    assert changes(before, snapshot(tmp_path)) == []


def test_train_with_a_broken_capture_is_one_line(tmp_path, capsys) -> None:
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "meta_data.json").write_text("{ not json")
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(capture), "--cache-dir", str(tmp_path / "cache")],
                 rf"^regnf train: {capture / 'meta_data.json'}: invalid JSON")
    assert changes(before, snapshot(tmp_path)) == []


@pytest.mark.parametrize("box, problem", [
    ({"center": [0, 0, 0], "size": [0.5, 0.0, 0.5]}, "'size' must be positive"),
    ({"center": [0, 0, 0], "size": [0.5, -0.5, 0.5]}, "'size' must be positive"),
    ({"center": [0, 0, float("nan")], "size": [1, 1, 1]}, "finite"),
    ({"corners": [[0, 0, 0]] * 8}, "not a usable box"),
    ({"corners": np.random.default_rng(0).normal(size=(8, 3)).tolist()}, "not a usable box"),
    ({"corners": [[0, 0, 0]] * 7}, "8 finite"),
    ([1, 2, 3], "a box is a JSON object"),
    ({"centre": [0, 0, 0]}, "expected 'corners' or 'center'"),
])
def test_a_bad_box_names_its_file_before_any_field_is_loaded(tmp_path, tiny, box, problem, monkeypatch,
                                                             capsys) -> None:
    monkeypatch.setattr(commands_registration, "load_field", _never)
    path = tmp_path / "bad_box.json"
    path.write_text(json.dumps(box))
    line = assert_fails(capsys, ["register", "--scene", str(tiny), "--library", str(tiny), "--box", str(path),
                                 "--out", str(tmp_path / "r.json")], str(path))
    assert problem in line
    assert not (tmp_path / "r.json").exists()


def test_a_box_file_that_is_not_json_names_it(tmp_path, tiny, monkeypatch, capsys) -> None:
    monkeypatch.setattr(commands_registration, "load_field", _never)
    path = tmp_path / "box.json"
    path.write_bytes(b"\xff\xfe\x00garbage")
    assert_fails(capsys, ["register", "--scene", str(tiny), "--library", str(tiny), "--box", str(path)],
                 rf"{path}: cannot read the box")


def test_register_into_a_missing_stage_fails_before_registering(tmp_path, tiny, good_box, monkeypatch,
                                                                capsys) -> None:
    monkeypatch.setattr(register_module, "register", _never)
    stage = tmp_path / "no_such_stage.usda"
    assert_fails(capsys, ["register", "--scene", str(tiny), "--library", str(tiny), "--box", str(good_box),
                          "--out", str(tmp_path / "r.json"), "--stage", str(stage)], str(stage))
    assert not (tmp_path / "r.json").exists()


def test_outputs_of_the_wrong_kind_are_refused_before_work(tmp_path, tiny, good_box, read_only_dir, monkeypatch,
                                                           capsys) -> None:
    monkeypatch.setattr(commands_fields, "load_field", _never)
    monkeypatch.setattr(commands_registration, "load_field", _never)
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    a_folder = tmp_path / "a_folder"
    a_folder.mkdir()
    before = snapshot(tmp_path)
    # A file where a folder is wanted, and the reverse; a folder below a file; a read-only file system.
    assert_fails(capsys, ["render", str(tmp_path / "missing.usda"), "--composite.mode", "scene", "--orbit", "1",
                          "--out", str(a_file)], rf"--out {a_file}: is a file, expected a folder")
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(a_folder)], "is a folder, expected a file")
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(a_file / "sub" / "m.ply")],
                 f"{a_file} is a file, not a folder")
    assert_fails(capsys, ["register", "--scene", str(tiny), "--library", str(tiny), "--box", str(good_box),
                          "--out", str(a_folder)], "is a folder, expected a file")
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(read_only_dir / "m.ply")],
                 f"the folder {read_only_dir} is not writable")
    assert_fails(capsys, ["render", str(tmp_path / "missing.usda"), "--composite.mode", "scene", "--orbit", "1",
                          "--out", str(read_only_dir / "renders")], f"the folder {read_only_dir} is not writable")
    assert_fails(capsys, ["train", "--capture", str(tmp_path), "--out", str(tmp_path / "f.ckpt")],
                 "must end in .safetensors")
    assert changes(before, snapshot(tmp_path)) == []


def test_limits_are_checked_before_anything_is_loaded(tmp_path, tiny, monkeypatch, capsys) -> None:
    monkeypatch.setattr(commands_fields, "load_field", _never)
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(tmp_path / "m.ply"), "--resolution", "100000"],
                 r"--resolution 100000 needs about .* GiB of memory")
    side = int(np.sqrt(MAX_PIXELS)) + 1
    assert_fails(capsys, ["render", str(tmp_path / "missing.usda"), "--composite.mode", "scene", "--orbit", "1",
                          "--width", "100000", "--height", "100000", "--out", str(tmp_path / "r")], "a view may have")
    assert_fails(capsys, ["render", str(tmp_path / "missing.usda"), "--composite.mode", "scene", "--orbit", "1",
                          "--width", str(side), "--height", str(side), "--out", str(tmp_path / "r")], "a view may have")
    assert_fails(capsys, ["render", str(tmp_path / "missing.usda"), "--composite.mode", "scene", "--orbit", "0",
                          "--out", str(tmp_path / "r")], "--orbit must be at least 1")
    assert not (tmp_path / "r").exists() and not (tmp_path / "m.ply").exists()


def test_a_composite_with_too_many_instances_is_refused_when_built() -> None:
    scene = Sphere(radius=0.5)
    place = torch.eye(4, dtype=torch.float64)
    objects = [PlacedObject(Sphere(radius=0.1), place, k + 1) for k in range(MAX_COMPONENTS + 1)]
    with pytest.raises(ValueError, match=f"at most {MAX_COMPONENTS} placed objects, got {MAX_COMPONENTS + 1}"):
        CompositeField(scene, objects)


def test_debug_shows_the_traceback(corrupt, tmp_path, capsys) -> None:
    status, err = run_cli(capsys, ["--debug", "mesh", "--field", str(corrupt), "--out", str(tmp_path / "m.ply")])
    assert status == EXIT_BAD_INPUT
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith(f"regnf mesh: {corrupt}")


def test_an_os_error_names_its_file_and_a_bug_says_so(tmp_path, tiny, monkeypatch, capsys) -> None:
    def denied(*args: object, **kwargs: object) -> None:
        raise PermissionError(13, "Permission denied", str(tmp_path / "locked.ply"))

    monkeypatch.setattr(commands_fields, "load_field", denied)
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(tmp_path / "m.ply")],
                 rf"^regnf mesh: {tmp_path / 'locked.ply'}: Permission denied$")

    def bug(*args: object, **kwargs: object) -> None:
        raise KeyError("oops")

    monkeypatch.setattr(commands_fields, "load_field", bug)
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(tmp_path / "m.ply")],
                 r"internal error \(KeyError: 'oops'\); rerun with --debug", status=EXIT_INTERNAL)


def test_usage_errors_keep_status_2(capsys) -> None:
    with pytest.raises(SystemExit) as done:
        main(["mesh", "--no-such-option"])
    assert done.value.code == 2


def test_the_readme_documents_every_exit_status() -> None:
    import re

    from regnf.cli import app as cli

    statuses = {v for k, v in vars(cli).items() if k.startswith("EXIT_")}
    readme = (Path(__file__).parents[2] / "README.md").read_text()
    table = readme.split("### When something is wrong", 1)[1].split("\n## ", 1)[0]
    documented = {int(m) for m in re.findall(r"^\| (\d+) \|", table, flags=re.MULTILINE)}
    assert documented == statuses


def test_a_stage_another_process_is_writing_gives_status_busy(tmp_path, monkeypatch, capsys) -> None:
    import sys

    from regnf.cli.app import EXIT_BUSY
    from regnf.scene_graph import locking
    from tests.scene_graph.helpers import make_stage, registration_json, similarity

    stage = make_stage(tmp_path / "stage", ("c", "t"))
    result = tmp_path / "c.json"
    result.write_text(json.dumps(registration_json("c", stage.parent / "fields" / "c.safetensors",
                                                   similarity(0.3, (1.0, 0.0, 0.0), 1.0))))
    before = snapshot(stage.parent)
    holder = subprocess.Popen(
        [sys.executable, "-c", ("import sys, time\nfrom regnf.core.file_lock import folder_lock\n"
                                f"with folder_lock({str(stage.parent)!r}):\n"
                                "    print('held', flush=True)\n    time.sleep(60)")],
        stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parents[2])
    try:
        assert holder.stdout.readline().strip() == "held"
        monkeypatch.setattr(locking, "STAGE_LOCK_TIMEOUT_S", 0.2)
        assert_fails(capsys, ["stage", "add-instance", str(stage), "--result", str(result)],
                     r"is in use by another regnf process \(pid \d+", status=EXIT_BUSY)
    finally:
        holder.kill()
        holder.wait()
    # The lock file holds the pid of its last holder (the other process); nothing else changed.
    assert [c for c in changes(before, snapshot(stage.parent)) if not c.endswith(".regnf.lock")] == []
