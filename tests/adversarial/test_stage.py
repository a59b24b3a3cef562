"""A hostile user against the stage: concurrent writers, paths that leave the stage's folder,
registration results that would make the stage unrenderable, private file modes, and a
stage that cannot be written.

Every refusal is a one-line ``StageError`` naming the file, and leaves the disk as it was.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf

from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.file_lock import LockBusy
from regnf.scene_graph import (
    StageError,
    add_instance,
    add_instance_from_registration,
    check_writable,
    export_stage,
    locking,
    make_replacement_layer,
    read_stage,
    replacement_base,
    stage_lock,
)
from tests.adversarial.disk import changes, snapshot
from tests.core.helpers import held_on_another_thread
from tests.scene_graph.helpers import make_stage, registration_json, similarity

WRITERS = 2
PER_WRITER = 20
"""Two processes each add this many instances to one stage at the same time."""


@pytest.fixture
def stage(tmp_path: Path) -> Path:
    """``tmp/main/stage/scene.usda`` with library c, dc, t and one instance ``c_1``."""
    path = make_stage(tmp_path / "main")
    add_instance(path, "c", similarity(0.5, (1.0, 1.0, 0.0), 1.0))
    return path


def _set_layer(path: Path, edit) -> None:
    """Edit the layer at ``path`` in place (as a user with a text editor would)."""
    layer = Sdf.Layer.FindOrOpen(str(path))
    edit(layer)
    layer.Save()


def _set_checkpoint(layer_path: Path, prim: str, asset: str) -> None:
    _set_layer(layer_path, lambda layer: setattr(
        layer.GetAttributeAtPath(f"{prim}.regnf:field:checkpoint"), "default", Sdf.AssetPath(asset)))


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    return text


# -- (a) concurrent writers ---------------------------------------------------------------------
def _writer(stage: str, k: int, barrier) -> None:
    """Add PER_WRITER instances of ``c`` at (k, i, 0), starting with the other writer."""
    barrier.wait(timeout=120)
    for i in range(PER_WRITER):
        add_instance(stage, "c", similarity(0.1 * i, (float(k), float(i), 0.0), 1.0))


def test_concurrent_writers_lose_nothing(tmp_path: Path) -> None:
    path = make_stage(tmp_path)
    ctx = multiprocessing.get_context("spawn")
    barrier = ctx.Barrier(WRITERS)
    procs = [ctx.Process(target=_writer, args=(str(path), k, barrier)) for k in range(WRITERS)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=240)
    assert [p.exitcode for p in procs] == [0] * WRITERS
    scene = read_stage(path)
    assert len(scene.instances) == WRITERS * PER_WRITER
    got = {tuple(np.round(inst.object_to_scene[:2, 3]).astype(int)) for inst in scene.instances.values()}
    assert got == {(k, i) for k in range(WRITERS) for i in range(PER_WRITER)}
    assert not [p for p in path.parent.rglob("*") if p.name.startswith(".regnf-tmp-")]


def test_a_held_lock_makes_a_writer_wait_then_give_up(stage: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(locking, "STAGE_LOCK_TIMEOUT_S", 0.3)
    with held_on_another_thread(lambda: stage_lock(stage)):
        before = snapshot(stage.parent)
        with pytest.raises(LockBusy, match="in use"):
            add_instance(stage, "dc", similarity(0.0, (0.0, 0.0, 0.0), 1.0))
        assert changes(before, snapshot(stage.parent)) == []
    add_instance(stage, "dc", similarity(0.0, (0.0, 0.0, 0.0), 1.0))  # free again
    assert "dc_1" in read_stage(stage).instances


# -- (b) asset paths that leave the stage's folder ----------------------------------------------
def test_a_package_path_outside_the_folder_is_refused(stage: Path, tmp_path: Path) -> None:
    other = export_stage(make_stage(tmp_path / "other"), tmp_path / "main" / "elsewhere" / "x.usdz")
    bad = "../elsewhere/x.usdz[fields/scene_field.usdc]"
    _set_checkpoint(stage, "/World/Scene", bad)
    before = snapshot(tmp_path / "main")
    for attempt in (lambda: read_stage(stage),
                    lambda: export_stage(stage, tmp_path / "main" / "out" / "s.usdz"),
                    lambda: export_stage(stage, tmp_path / "main" / "out" / "s.usda"),
                    lambda: composite_from_stage(stage, StageCompositeConfig(mode="scene"))):
        with pytest.raises(StageError) as err:
            attempt()
        text = _one_line(err)
        assert bad in text and str(stage) in text and "prim /World/Scene" in text and "escapes" in text
    assert changes(before, snapshot(tmp_path / "main")) == []
    # Asked for explicitly, it is read, and an export carries the field in: self-contained.
    assert str(other) in str(read_stage(stage, allow_outside=True).scene.checkpoint)
    out = export_stage(stage, tmp_path / "pkg" / "s.usdz", allow_outside=True)
    assert str(out) in str(read_stage(out).scene.checkpoint)


@pytest.mark.parametrize("how", ["relative", "absolute", "symlink"])
def test_a_layer_outside_the_folder_is_never_opened(stage: Path, tmp_path: Path, how: str) -> None:
    outside = tmp_path / "elsewhere" / "extra.usda"
    outside.parent.mkdir()
    Sdf.Layer.CreateNew(str(outside)).Save()
    if how == "relative":
        rel = "../../elsewhere/extra.usda"
    elif how == "absolute":
        rel = str(outside)
    else:
        (stage.parent / "extra.usda").symlink_to(outside)
        rel = "./extra.usda"
    _set_layer(stage, lambda layer: layer.subLayerPaths.append(rel))
    assert Sdf.Layer.Find(str(outside)) is None
    with pytest.raises(StageError) as err:
        read_stage(stage)
    text = _one_line(err)
    assert rel in text and str(stage) in text and "prim /:" in text
    assert Sdf.Layer.Find(str(outside)) is None and Sdf.Layer.Find(str(stage.parent / "extra.usda")) is None
    # The same path as a checkpoint, in a library layer: refused as well, naming that layer.
    _set_layer(stage, lambda layer: layer.subLayerPaths.remove(rel))
    lib = stage.parent / "library" / "c.usda"
    target = tmp_path / "elsewhere" / "c.safetensors"
    target.write_bytes((stage.parent / "fields" / "c.safetensors").read_bytes())
    if how == "symlink":
        (stage.parent / "fields" / "c_link.safetensors").symlink_to(target)
        asset = "../fields/c_link.safetensors"
    else:
        asset = str(target) if how == "absolute" else "../../../elsewhere/c.safetensors"
    _set_checkpoint(lib, "/c", asset)
    with pytest.raises(StageError) as err:
        read_stage(stage)
    text = _one_line(err)
    assert asset in text and str(lib) in text and "prim /c" in text


@pytest.mark.parametrize("target", ["sibling", "/etc/passwd"])
def test_replacement_of_outside_the_folder_is_not_followed(stage: Path, tmp_path: Path, target: str) -> None:
    layer = make_replacement_layer(stage, {"c_1": "dc"}, stage.parent / "swap.usda")
    if target == "sibling":
        sibling = make_stage(tmp_path / "sib")
        rel, ident = "../../sib/stage/scene.usda", str(sibling)
    else:
        rel = ident = target

    def point_away(lay: Sdf.Layer) -> None:
        data = dict(lay.customLayerData)
        data["regnf"]["replacementOf"] = rel
        lay.customLayerData = data

    _set_layer(layer, point_away)
    assert Sdf.Layer.Find(ident) is None
    for attempt in (lambda: read_stage(layer), lambda: replacement_base(layer),
                    lambda: composite_from_stage(layer)):
        with pytest.raises(StageError) as err:
            attempt()
        text = _one_line(err)
        assert rel in text and str(layer) in text and "replacementOf" in text
        assert Sdf.Layer.Find(ident) is None  # refused before the file was opened


# -- (c) registration results that would make the stage unrenderable -------------------------------
def _bad_result(kind: str, lib: Path) -> tuple[dict, str]:
    """A registration result that is wrong in one way, and the key the message must name."""
    M = similarity(0.4, (0.5, 0.5, 0.0), 1.0)
    r = registration_json("dc", lib, M)
    if kind == "zero box":
        r["proposal_box"]["half_extents"] = [0.3, 0.0, 0.45]
        return r, "half extents"
    if kind == "reflected box":
        r["proposal_box"]["rotation"] = np.diag([1.0, 1.0, -1.0]).tolist()
        return r, "rotation"
    if kind == "reflected transform":
        r["object_to_scene_metres"] = (M @ np.diag([1.0, -1.0, 1.0, 1.0])).tolist()
        return r, "object_to_scene_metres"
    if kind == "non-uniform transform":
        r["object_to_scene_metres"] = (M @ np.diag([1.0, 1.0, 1.5, 1.0])).tolist()
        return r, "object_to_scene_metres"
    if kind == "reflected scene_to_library":
        r["transform_scene_to_library"]["matrix"] = (-np.eye(4) + np.diag([0, 0, 0, 2.0])).tolist()
        return r, "scene_to_library"
    if kind == "accepted string":
        r["accepted"] = "false"
        return r, "accepted"
    if kind == "nan confidence":
        r["confidence"] = math.nan
        return r, "confidence"
    if kind == "string matrix":
        r["object_to_scene_metres"] = [[str(v) for v in row] for row in M.tolist()]
        return r, "object_to_scene_metres"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["zero box", "reflected box", "reflected transform", "non-uniform transform",
                                  "reflected scene_to_library", "accepted string", "nan confidence",
                                  "string matrix"])
def test_an_unrenderable_registration_is_not_written(stage: Path, kind: str) -> None:
    result, key = _bad_result(kind, stage.parent / "fields" / "dc.safetensors")
    before = snapshot(stage.parent)
    with pytest.raises(StageError) as err:
        add_instance_from_registration(stage, result)
    text = _one_line(err)
    assert str(stage) in text and key in text and "registration result" in text
    assert changes(before, snapshot(stage.parent)) == []
    with pytest.raises(StageError):  # forcing does not make it renderable either
        add_instance_from_registration(stage, result, force=True)
    assert changes(before, snapshot(stage.parent)) == []


def test_the_reader_applies_the_writer_rules(stage: Path) -> None:
    lib = stage.parent / "fields" / "dc.safetensors"
    iid = add_instance_from_registration(stage, registration_json("dc", lib, similarity(0.4, (0.5, 0.5, 0.0), 1.0)))
    comp = composite_from_stage(stage)  # what is written renders
    assert iid in comp.instance_ids
    attr = f"/World/Instances/{iid}.regnf:registration:proposal:halfExtents"
    _set_layer(stage, lambda layer: setattr(layer.GetAttributeAtPath(attr), "default", (0.3, 0.0, 0.45)))
    with pytest.raises(StageError) as err:
        read_stage(stage)
    text = _one_line(err)
    assert f"/World/Instances/{iid}" in text and "half extents" in text and str(stage) in text


# -- (d) file modes follow the umask ---------------------------------------------------------------
@pytest.fixture(params=[0o022, 0o002], ids=["umask022", "umask002"])
def umask(request: pytest.FixtureRequest) -> Iterator[int]:
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _modes_wrong(folder: Path, umask: int) -> list[str]:
    """Entries under ``folder`` whose mode is not what ``open`` / ``mkdir`` give under ``umask``."""
    wrong = []
    for p in sorted(folder.rglob("*")):
        want = (0o777 if p.is_dir() else 0o666) & ~umask
        got = p.stat().st_mode & 0o777
        if got != want:
            wrong.append(f"{p.relative_to(folder)}: {oct(got)}, expected {oct(want)}")
    return wrong


def test_files_get_the_umask_mode(tmp_path: Path, umask: int) -> None:
    path = make_stage(tmp_path)  # a new stage
    assert _modes_wrong(path.parent, umask) == []
    add_instance(path, "c", similarity(0.2, (1.0, 0.0, 0.0), 1.0))  # an edit rewrites files
    make_replacement_layer(path, {"c_1": "dc"}, path.parent / "swap.usda")
    assert _modes_wrong(path.parent, umask) == []
    export_stage(path, tmp_path / "pkg" / "scene.usdz")
    export_stage(path, tmp_path / "copy" / "scene.usdc")
    assert _modes_wrong(tmp_path / "pkg", umask) == []
    assert _modes_wrong(tmp_path / "copy", umask) == []


# -- (e) check_writable ----------------------------------------------------------------------------
CHECK = """
import sys
from regnf.scene_graph import StageError, check_writable
try:
    check_writable(sys.argv[1])
except StageError as exc:
    print("REFUSED", exc)
else:
    print("ACCEPTED")
"""


def test_check_writable(stage: Path, tmp_path: Path) -> None:
    assert check_writable(stage) == stage
    with pytest.raises(StageError, match="no such stage file") as err:
        check_writable(tmp_path / "missing.usda")
    assert str(tmp_path / "missing.usda") in _one_line(err)
    foreign = tmp_path / "foreign.usda"
    Sdf.Layer.CreateNew(str(foreign)).Save()
    with pytest.raises(StageError, match="not a regnf stage"):
        check_writable(foreign)
    usdz = export_stage(stage, tmp_path / "pkg" / "s.usdz")
    with pytest.raises(StageError, match="export a package"):
        check_writable(usdz)


def _as_another_user(path: str | os.PathLike, mode: int, *, effective_ids: bool = False) -> bool:
    """``os.access`` for a user who neither owns ``path`` nor is in its group (the "other" bits)."""
    bits = {os.R_OK: 0o004, os.W_OK: 0o002, os.X_OK: 0o001}
    perm = os.stat(path).st_mode
    return all(perm & bit for flag, bit in bits.items() if mode & flag)


def test_check_writable_refuses_a_read_only_folder(monkeypatch: pytest.MonkeyPatch) -> None:
    folder = Path(tempfile.mkdtemp(prefix="regnf-ro-"))
    try:
        os.chmod(folder, 0o755)  # others may enter: the check may run as another user below
        path = make_stage(folder)
        os.chmod(path.parent, 0o555)
        if os.geteuid() != 0:
            with pytest.raises(StageError, match="not writable") as err:
                check_writable(path)
            assert str(path.parent) in _one_line(err)
            return
        # root writes anywhere: run the check as an unprivileged user, for whom it is read-only.
        try:
            proc = subprocess.run([sys.executable, "-c", CHECK, str(path)], check=False, user=65534, group=65534,
                                  extra_groups=[], cwd=Path(__file__).resolve().parents[2],
                                  capture_output=True, text=True, timeout=120)
        except PermissionError:
            # That user cannot run this interpreter (it lives in root's home): ask the same
            # question the kernel would answer for them instead.
            monkeypatch.setattr(locking.os, "access", _as_another_user)
            with pytest.raises(StageError, match="not writable") as err:
                check_writable(path)
            assert str(path.parent) in _one_line(err)
            return
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith("REFUSED") and "not writable" in proc.stdout, proc.stdout
        assert str(path.parent) in proc.stdout
    finally:
        if (folder / "stage").exists():
            os.chmod(folder / "stage", 0o755)
        shutil.rmtree(folder, ignore_errors=True)


def test_a_command_holding_its_output_folder_can_write_and_export_a_stage_in_it(tmp_path: Path) -> None:
    # As regnf demo does: its folder's lock is held while the stage and the package are written there.
    from regnf.core.output_dir import owned_output_dir
    from regnf.scene_graph import export_stage

    out = tmp_path / "demo"
    with owned_output_dir(out, "test-command"):
        stage = make_stage(out, ("c", "t"))
        export_stage(stage, out / "room.usdz")
    assert (out / "room.usdz").is_file()
