"""Inputs that are not what they claim to be: a JSON option naming ``/dev/zero``, a FIFO, a
folder or a huge file; a stage path that is a folder, a FIFO or a device; a stage whose
instance transforms hold NaN or infinity.

Each is refused at once (a FIFO is never opened: that would wait for a writer for ever, and
``/dev/zero`` never ends), with one line naming the option, the file (and prim) and the
problem, exit status 1, and nothing on disk changed. Special files live outside the folder
that is snapshotted (reading a FIFO to hash it would block the test itself).
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import threading
import time
from pathlib import Path

import pytest
from pxr import Gf, Usd

from regnf.cli import commands_registration
from regnf.core.preflight import MAX_JSON_BYTES
from regnf.scene_graph import add_instance
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails, run_cli
from tests.scene_graph.helpers import make_stage, registration_json, similarity

AT_ONCE_S = 1.0
"""A refusal of a special file takes less than this, in seconds (reading a FIFO or /dev/zero would never end)."""
BLOCKED_S = 20.0
"""Seconds after which a command that has not returned is taken to be blocked (on a FIFO, reading /dev/zero)."""
INSTANCE = "/World/Instances/c_1"
"""The instance prim of the test stage."""


def _never(*args: object, **kwargs: object) -> None:
    raise AssertionError("the command started its work before checking its inputs")


@pytest.fixture(scope="module")
def stage_src(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny valid stage (library c, dc, t) with one instance ``c_1``; copied by the tests that change it."""
    path = make_stage(tmp_path_factory.mktemp("inputs"))
    add_instance(path, "c", similarity(0.5, (1.0, 1.0, 0.0), 1.0))
    return path


@pytest.fixture()
def work(tmp_path: Path, stage_src: Path) -> Path:
    """``tmp/work``: a copy of the test stage's folder (``stage/``, ``src/``), the only folder snapshotted."""
    root = tmp_path / "work"
    shutil.copytree(stage_src.parent.parent, root)
    return root


@pytest.fixture(params=["dev_zero", "fifo", "folder"])
def special(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    """(a path that is no regular file, the kind the message must name), outside ``work``."""
    folder = tmp_path / "special"
    folder.mkdir()
    if request.param == "dev_zero":
        return Path("/dev/zero"), "a character device"
    if request.param == "fifo":
        path = folder / "input.usda"
        os.mkfifo(path)
        return path, "a FIFO"
    path = folder / "folder.usda"
    path.mkdir()
    return path, "a folder"


def _fails_at_once(capsys: pytest.CaptureFixture[str], args: list[str], pattern: str, special: Path) -> str:
    """``assert_fails`` within :data:`AT_ONCE_S`; a command that blocks fails the test instead of hanging it.

    The command first runs once with a missing file in place of ``special``, untimed, so that
    the time measured is the refusal's, not the imports of the command's modules.
    """
    run_cli(capsys, ["/dev/null/warm-up.usda" if a == str(special) else a for a in args])
    outcome: dict[str, object] = {}

    def attempt() -> None:
        t0 = time.perf_counter()
        try:
            outcome["line"] = assert_fails(capsys, args, pattern)
        except BaseException as exc:  # noqa: BLE001 (re-raised in the test's thread)
            outcome["error"] = exc
        outcome["seconds"] = time.perf_counter() - t0

    thread = threading.Thread(target=attempt, daemon=True)
    thread.start()
    thread.join(BLOCKED_S)
    assert not thread.is_alive(), f"regnf {' '.join(args[:2])} still runs after {BLOCKED_S} s: it blocked"
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    assert outcome["seconds"] < AT_ONCE_S, f"took {outcome['seconds']:.2f} s: {outcome['line']}"
    return str(outcome["line"])


# -- JSON inputs ------------------------------------------------------------------------------
def _json_commands(work: Path, path: Path) -> list[tuple[list[str], str]]:
    """(arguments, option) of every command that reads a JSON file the user names, given ``path``."""
    src = work / "src"
    return [
        (["register", "--scene", str(src / "room.safetensors"), "--library", str(src / "c.safetensors"),
          "--box", str(path), "--out", str(work / "r.json")], "--box"),
        (["stage", "add-instance", str(work / "stage" / "scene.usda"), "--result", str(path)], "--result"),
    ]


def test_a_json_option_naming_a_special_file_is_refused_at_once(work, special, monkeypatch, capsys) -> None:
    monkeypatch.setattr(commands_registration, "load_field", _never)
    path, kind = special
    before = snapshot(work)
    for args, option in _json_commands(work, path):
        _fails_at_once(capsys, args, rf": {option} {path}: is not a file \({kind}\)$", path)
    assert changes(before, snapshot(work)) == []


def test_a_json_file_larger_than_the_cap_is_refused_unread(work, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(commands_registration, "load_field", _never)
    huge = tmp_path / "huge.json"
    with open(huge, "wb") as f:  # sparse: no bytes written, the size is what counts
        f.truncate(MAX_JSON_BYTES + 1)
    before = snapshot(work)
    for args, option in _json_commands(work, huge):
        _fails_at_once(capsys, args, rf": {option} {huge}: {MAX_JSON_BYTES + 1:,} bytes, more than the "
                                     rf"{MAX_JSON_BYTES:,} a .* may have", huge)
    assert changes(before, snapshot(work)) == []


def test_a_missing_or_non_utf8_json_option_names_option_and_file(work, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(commands_registration, "load_field", _never)
    missing, latin = tmp_path / "missing.json", tmp_path / "latin.json"
    latin.write_bytes('{"confidence": "\xe9"}'.encode("latin-1"))
    before = snapshot(work)
    for args, option in _json_commands(work, missing):
        _fails_at_once(capsys, args, rf": {option} {missing}: no such ", missing)
    for args, option in _json_commands(work, latin):
        _fails_at_once(capsys, args, rf": {option} {latin}: cannot read the .* \(not UTF-8 JSON: ", latin)
    assert changes(before, snapshot(work)) == []


def test_a_checkpoint_or_mesh_that_is_a_special_file_is_refused_at_once(work, special, capsys) -> None:
    path, kind = special
    before = snapshot(work)
    _fails_at_once(capsys, ["mesh", "--field", str(path), "--out", str(work / "m.ply")],
                   rf"^regnf mesh: {path}: is not a file \({kind}\)$", path)
    _fails_at_once(capsys, ["distill", "--mesh", str(path), "--cache-dir", str(work / "cache")],
                   rf"^regnf distill: --mesh {path}: is not a file \({kind}\)$", path)
    assert changes(before, snapshot(work)) == []


# -- the stage --------------------------------------------------------------------------------
def _stage_commands(work: Path, stage: Path, result: Path, box: Path) -> list[list[str]]:
    """Every command that opens a stage, given ``stage``; outputs go to ``work/out*``."""
    src = work / "src"
    out = str(work / "out")
    return [
        ["render", str(stage), "--orbit", "1", "--width", "8", "--height", "6", "--out", out],
        ["replace", str(stage), "--orbit", "1", "--width", "8", "--height", "6", "--out", out],
        ["view", str(stage)],
        ["generate", str(stage), "--out", out],
        ["stage", "show", str(stage)],
        ["stage", "add-instance", str(stage), "--result", str(result)],
        ["stage", "export", str(stage), "--usda", str(work / "out.usda")],
        ["register", "--scene", str(src / "room.safetensors"), "--library", str(src / "c.safetensors"),
         "--box", str(box), "--out", str(work / "r.json"), "--stage", str(stage)],
    ]


def test_a_stage_that_is_a_folder_fifo_or_device_is_not_a_file(work, special, tmp_path, monkeypatch,
                                                               capsys) -> None:
    monkeypatch.setattr(commands_registration, "load_field", _never)
    path, kind = special
    result = tmp_path / "result.json"
    result.write_text(json.dumps(registration_json("c", work / "src" / "c.safetensors", similarity(0, (1, 1, 0), 1))))
    box = tmp_path / "box.json"
    box.write_text(json.dumps({"center": [1, 1, 0.4], "size": [0.5, 0.5, 0.9]}))
    before = snapshot(work)
    for args in _stage_commands(work, path, result, box):
        _fails_at_once(capsys, args, rf"^regnf [^:]+: {path}: is not a file \({kind}\)$", path)
    if path.suffix == ".usda":  # discover takes only a .usda or .usdc stage
        _fails_at_once(capsys, ["discover", "--scene", str(work / "src" / "room.safetensors"), "--library",
                                str(work / "src" / "c.safetensors"), "--out", str(work / "found"), "--stage",
                                str(path)], rf"^regnf discover: {path}: is not a file \({kind}\)$", path)
    assert changes(before, snapshot(work)) == []


# -- non-finite transforms --------------------------------------------------------------------
def _set_object_to_scene(prim: Usd.Prim, value: float) -> None:
    M = Gf.Matrix4d(prim.GetAttribute("regnf:objectToScene").Get())
    row = M.GetRow(3)  # USD rows: the translation is the last row
    row[0] = value
    M.SetRow(3, row)
    prim.GetAttribute("regnf:objectToScene").Set(M)


def _set_translate(prim: Usd.Prim, value: float) -> None:
    attr = prim.GetAttribute("xformOp:translate")
    t = attr.Get()
    attr.Set(type(t)(value, t[1], t[2]))


def _set_orient(prim: Usd.Prim, value: float) -> None:
    attr = prim.GetAttribute("xformOp:orient")
    q = attr.Get()
    attr.Set(type(q)(value, q.GetImaginary()))


def _set_scale(prim: Usd.Prim, value: float) -> None:
    attr = prim.GetAttribute("xformOp:scale")
    attr.Set(type(attr.Get())(value, value, value))


@pytest.mark.parametrize(("attribute", "setter", "value"), [
    ("regnf:objectToScene", _set_object_to_scene, math.nan),
    ("regnf:objectToScene", _set_object_to_scene, math.inf),
    ("xformOp:translate", _set_translate, math.nan),
    ("xformOp:translate", _set_translate, -math.inf),
    ("xformOp:orient", _set_orient, math.nan),
    ("xformOp:scale", _set_scale, math.inf),
])
def test_a_non_finite_instance_transform_names_file_prim_and_attribute(work, attribute, setter, value,
                                                                        capsys) -> None:
    stage_path = work / "stage" / "scene.usda"
    stage = Usd.Stage.Open(str(stage_path))  # plain USD, as a user's script or editor would write it
    setter(stage.GetPrimAtPath(INSTANCE), value)
    stage.GetRootLayer().Save()
    authored = next(line for line in stage_path.read_text().splitlines() if f" {attribute} = " in line)
    assert re.search(r"\b(nan|inf)\b", authored), authored  # the file holds it
    before = snapshot(work)
    problem = rf"{stage_path}: prim {INSTANCE}: '{attribute}' has non-finite entries: "
    assert_fails(capsys, ["stage", "show", str(stage_path)], rf"^regnf stage: {problem}")
    assert_fails(capsys, ["stage", "export", str(stage_path), "--usda", str(work / "out" / "s.usda")],
                 rf"^regnf stage: {problem}")
    assert_fails(capsys, ["render", str(stage_path), "--orbit", "1", "--width", "8", "--height", "6",
                          "--out", str(work / "renders")], rf"^regnf render: {problem}")
    assert changes(before, snapshot(work)) == []  # nothing exported, nothing rendered
