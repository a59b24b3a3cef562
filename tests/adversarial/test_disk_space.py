"""A read-only cache, an output folder nobody may write, a disk too small for a data set or its
baked grids, a disk that fills up during a write.

Each is refused before the long work (training, distilling, discovering, baking, rendering),
with one line naming the folder or file and the figures, exit status 1, and nothing on disk
changed; a write that fails names the file it was writing, not a temporary one. Read-only and
small disks are tmpfs mounts (root; skipped elsewhere), so the file system itself refuses.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

import regnf.cli.demo as demo_module
from regnf.captures.sdfstudio import write_capture
from regnf.cli.app import EXIT_BAD_INPUT, _one_line, exit_status
from regnf.core import atomic_io
from regnf.core.atomic_io import TEMP_PREFIX, write_json
from regnf.core.executors import ExecutorConfig
from regnf.core.preflight import PreflightError
from regnf.datasets.generation import BAKED_DIR, GenerateConfig, generate
from regnf.scene_graph import add_instance
from regnf.synthetic import cache as cache_module
from tests.adversarial.disk import changes, snapshot
from tests.adversarial.mounts import tmpfs
from tests.cli.cli_helpers import assert_fails
from tests.datasets.test_generate import ORBIT
from tests.scene_graph.helpers import checkpoint, make_stage, similarity


def _never(*args: object, **kwargs: object) -> None:
    raise AssertionError("the command started its long work before checking where it writes")


@pytest.fixture()
def read_only(tmp_path: Path) -> Path:
    """A read-only file system (a tmpfs mounted ro): no write succeeds there, not even root's."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    with tmpfs(folder, "ro,size=64k"):
        yield folder


@pytest.fixture()
def small_disk(tmp_path: Path) -> Path:
    """A writable file system of 1 MiB."""
    folder = tmp_path / "small"
    folder.mkdir()
    with tmpfs(folder, "size=1m"):
        yield folder


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny stage (library c, dc, t; an instance of c)."""
    path = make_stage(tmp_path_factory.mktemp("disk_space"))
    add_instance(path, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    return path


def _capture(folder: Path) -> Path:
    """A valid two-frame capture (flat images: training never starts in these tests)."""
    rgb = [np.full((8, 8, 3), 128, np.uint8)] * 2
    depth = [np.ones((8, 8))] * 2
    poses = np.stack([np.eye(4)] * 2)
    poses[1, 0, 3] = 0.1
    K = np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]])
    write_capture(folder, rgb, depth, poses, K, np.eye(4))
    return folder


# -- read-only cache and output folders ---------------------------------------------------------
def test_a_read_only_cache_is_refused_before_training_or_distilling(tmp_path, read_only, monkeypatch,
                                                                    capsys) -> None:
    monkeypatch.setattr(cache_module, "train_rgbd", _never)
    monkeypatch.setattr(cache_module, "distill_mesh", _never)
    monkeypatch.setattr(demo_module, "run_demo", _never)
    capture = _capture(tmp_path / "capture")
    mesh = tmp_path / "box.ply"
    trimesh.creation.box(extents=(0.4, 0.3, 0.2)).export(mesh)
    cache = read_only / "cache"
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(capture), "--cache-dir", str(cache)],
                 rf"^regnf train: --cache-dir {cache / 'fields'}: the folder {read_only} is not writable$")
    assert_fails(capsys, ["distill", "--mesh", str(mesh), "--cache-dir", str(cache)],
                 rf"^regnf distill: --cache-dir {cache / 'fields'}: the folder {read_only} is not writable$")
    assert_fails(capsys, ["demo", "--out", str(tmp_path / "demo"), "--cache-dir", str(cache)],
                 rf"^regnf demo: --cache-dir {cache}: the folder {read_only} is not writable$")
    assert changes(before, snapshot(tmp_path)) == []


def test_an_output_folder_nobody_may_write_is_refused_first(tmp_path, stage, read_only, monkeypatch,
                                                             capsys) -> None:
    from regnf.cli import commands_discover

    monkeypatch.setattr(commands_discover, "load_field", _never)
    scene, chair = checkpoint(tmp_path, "room", "scene", scale=3.0), checkpoint(tmp_path, "c", "chair")
    before = snapshot(tmp_path)
    out = read_only / "out"
    assert_fails(capsys, ["generate", str(stage), "--out", str(out)],
                 rf"^regnf generate: --out {out}: the folder {read_only} is not writable$")
    assert_fails(capsys, ["discover", "--scene", str(scene), "--library", str(chair), "--out", str(out)],
                 rf"^regnf discover: --out {out}: the folder {read_only} is not writable$")
    assert changes(before, snapshot(tmp_path)) == []


# -- a disk too small -------------------------------------------------------------------------
def _config(**changes_: object) -> GenerateConfig:
    return dataclasses.replace(GenerateConfig(variants=1, cameras=ORBIT, executor=ExecutorConfig(workers=1)),
                               **changes_)


def test_a_data_set_larger_than_the_free_space_is_refused_before_anything_is_written(stage, small_disk,
                                                                                       capsys) -> None:
    out = small_disk / "data"
    before = snapshot(small_disk)
    variants = 200  # their views alone: 200 x 3 x 24 x 18 pixels x 10 bytes = 2.6 MB, on a disk of 1 MiB
    line = assert_fails(capsys, ["generate", str(stage), "--out", str(out), "--variants", str(variants),
                                 "--cameras.n", "3", "--cameras.width", "24", "--cameras.height", "18",
                                 "--cameras.radius", "4.5"],
                        rf"^regnf generate: writing {variants} variants \(3 views of 24 x 18 pixels each, "
                        rf"uncompressed\) and the base stage needs about [0-9.]+ MB in {out}, [0-9.]+ MB free")
    needed, free = (float(x) for x in re.findall(r"about ([0-9.]+) MB in .*, ([0-9.]+) MB free", line)[0])
    assert needed > variants * (3 * 24 * 18 * 10) / 1e6 > 2**20 / 1e6
    assert free <= round(2**20 / 1e6, 2)  # the 1 MiB disk, empty
    assert changes(before, snapshot(small_disk)) == []  # not even the folder, its marker or its lock


def test_baked_grids_that_do_not_fit_are_refused_before_baking(stage, small_disk, monkeypatch) -> None:
    from regnf.compositor import baked_composite

    monkeypatch.setattr(baked_composite, "bake", _never)  # no field is baked
    out = small_disk / "data"
    config = _config(render=dataclasses.replace(GenerateConfig().render, renderer="baked"))
    with pytest.raises(PreflightError, match=rf"^baking [0-9,]+ grid nodes and writing the variants needs about "
                                             rf"[0-9.]+ MB in {out / BAKED_DIR}, [0-9.]+ MB free") as err:
        generate(stage, out, config, progress=False)
    assert "\n" not in str(err.value)
    # The data set's base stage was exported (it fits); no grid file and no variant was written.
    assert not (out / BAKED_DIR).exists() or not any((out / BAKED_DIR).iterdir())
    assert not (out / "variants").exists() or not any((out / "variants").iterdir())


# -- a write that fails -----------------------------------------------------------------------
def test_a_full_disk_names_the_file_being_written(tmp_path, small_disk, capsys) -> None:
    tiny = checkpoint(tmp_path, "c", "chair")
    (small_disk / "filler").write_bytes(b"\0" * (1024 * 1024 - 64 * 1024))  # 64 KB left
    before = snapshot(small_disk)
    out = small_disk / "mesh.ply"
    assert_fails(capsys, ["mesh", "--field", str(tiny), "--out", str(out), "--resolution", "64"],
                 rf"^regnf mesh: {out}: No space left on device \(free some space, or write elsewhere, and run "
                 rf"again\)$")
    assert changes(before, snapshot(small_disk)) == []  # the temporary file is gone too


def test_an_error_without_a_file_name_inside_an_atomic_write_names_the_destination(tmp_path,
                                                                                    monkeypatch) -> None:
    def full(src: object, dst: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a full disk reports a flush: no name

    monkeypatch.setattr(atomic_io.os, "replace", full)
    dest = tmp_path / "record.json"
    with pytest.raises(OSError) as err:
        write_json(dest, {"a": 1})
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(dest)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(TEMP_PREFIX)] == []
    assert not dest.exists()
    assert exit_status(err.value) == EXIT_BAD_INPUT
    assert _one_line(err.value) == f"{dest}: No space left on device (free some space, or write elsewhere, and run again)"
