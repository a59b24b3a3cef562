"""``regnf discover``: a room with a chair and a lamp, a library of a chair and a table; the
chair is found, identified and written to the stage with how it was found, the lamp stays
unmatched; bad input is refused before any work, and nothing is written then.

Checkpoint loading is replaced by exact analytic fields (discovery itself runs for real), so
the test needs no trained field; the stage holds tiny real checkpoints.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import regnf.cli.commands_discover as commands
from regnf.cli.app import main
from regnf.fields.analytic import Box, Cylinder, Transformed, Union
from regnf.scene_graph import new_stage, read_stage
from tests.adversarial.disk import changes, snapshot
from tests.registration.fixtures import OBJECT_HI, OBJECT_LO, make_object, placement
from tests.scene_graph.helpers import checkpoint, make_library, make_stage

CHAIR_TO_SCENE = placement([0, 0, 1], 0.7, [1.0, -0.5, 0.0], 1.0)
# One process: the analytic fields patched in are not in the checkpoints workers would load.
FAST = ["--discovery.candidates.resolution", "128", "--discovery.shortlist", "2", "--discovery.workers", "1"]


def _printed(capsys: pytest.CaptureFixture[str]) -> str:
    cap = capsys.readouterr()
    return " ".join((cap.out + cap.err).split())


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A stage made from tiny checkpoints (scene, c, t) and the analytic field each path loads as."""
    folder = tmp_path_factory.mktemp("discover")
    stage = make_stage(folder, ("c", "t"))
    src = folder / "src"
    chair = make_object()
    chair.info.name = "c"
    table = Union(Box((0.4, 0.4, 0.03), (0.0, 0.0, 0.72)), Cylinder(0.06, 0.35, (0.0, 0.0, 0.35)),
                  label="table", name="t")
    room = Union(Box((3.0, 3.0, 0.05), (0.0, 0.0, -0.05)), Transformed(make_object(), CHAIR_TO_SCENE),
                 Cylinder(0.12, 0.7, (-1.0, 1.2, 0.7)), label="scene", name="room")
    fields = {str(src / "room.safetensors"): room, str(src / "c.safetensors"): chair,
              str(src / "t.safetensors"): table}
    return {"folder": folder, "stage": stage, "src": src, "fields": fields}


@pytest.fixture()
def patched(setup: dict, monkeypatch: pytest.MonkeyPatch) -> dict:
    monkeypatch.setattr(commands, "load_field", lambda path, device="cpu": setup["fields"][str(path)])
    return setup


def _args(setup: dict, out: Path, *extra: str) -> list[str]:
    src = setup["src"]
    return ["discover", "--scene", str(src / "room.safetensors"), "--library", str(src / "c.safetensors"),
            str(src / "t.safetensors"), "--out", str(out), *FAST, *extra]


def test_the_chair_is_written_with_how_it_was_found_and_the_lamp_is_not(patched, capsys) -> None:
    out = patched["folder"] / "out"
    assert main(_args(patched, out, "--stage", str(patched["stage"]))) == 0
    text = _printed(capsys)
    assert "unmatched" in text and "discovered 1 instances in 2 candidates" in text
    scene = read_stage(patched["stage"])
    assert len(scene.instances) == 1
    (iid, inst), = scene.instances.items()
    assert inst.library_name == "c"
    centre = CHAIR_TO_SCENE[:3, :3] @ ((OBJECT_LO + OBJECT_HI) / 2) + CHAIR_TO_SCENE[:3, 3]
    placed = inst.object_to_scene[:3, :3] @ ((OBJECT_LO + OBJECT_HI) / 2) + inst.object_to_scene[:3, 3]
    np.testing.assert_allclose(placed, centre, atol=0.01)
    record = inst.registration.discovery
    assert record["found_by"] == "discovery" and record["chosen"] == "c"
    assert record["tried"][0]["library"] == "c"
    assert record["tried"][0]["accepted"] is True
    saved = json.loads((out / "discovery.json").read_text())
    assert sorted(str(c["chosen"]) for c in saved["candidates"]) == ["None", "c"]
    assert [c["stage_instance"] for c in saved["candidates"] if c["chosen"]] == [iid]
    assert len(list((out / "registration").glob("candidate_*.json"))) == 1
    assert (out / "top_view.png").stat().st_size > 1000
    assert main(["stage", "show", str(patched["stage"])]) == 0
    assert "found by discovery (tried c " in _printed(capsys)


def test_a_stage_of_another_scene_is_refused_before_any_work(patched, tmp_path, capsys) -> None:
    _, libs, proxies = make_library(tmp_path / "other", ("c",))
    scene = checkpoint(tmp_path / "other", "room", "scene", scale=3.0, seed=7)  # other weights
    other = tmp_path / "other" / "stage" / "scene.usda"
    new_stage(other, scene, libs, proxies=proxies)
    before = snapshot(tmp_path)
    assert main(_args(patched, tmp_path / "out", "--stage", str(other))) == 1
    assert "is not the field of --scene" in _printed(capsys)
    assert not changes(before, snapshot(tmp_path))


@pytest.mark.parametrize("problem", ["no library", "missing scene", "foreign output", "bad stage suffix"])
def test_bad_input_is_one_line_and_writes_nothing(patched, tmp_path, capsys, problem) -> None:
    out = tmp_path / "out"
    args = _args(patched, out)
    if problem == "no library":
        i = args.index("--library")
        args = args[:i] + args[i + 3:]
    elif problem == "missing scene":
        args[args.index("--scene") + 1] = str(tmp_path / "nope.safetensors")
    elif problem == "foreign output":
        out.mkdir()
        (out / "notes.txt").write_text("mine")
    else:
        args += ["--stage", str(tmp_path / "stage.txt")]
    before = snapshot(tmp_path)
    try:
        status = main(args)
    except SystemExit as exc:  # tyro's usage error: status 2, the usage printed
        status = exc.code
    text = _printed(capsys)
    assert status == (2 if problem == "no library" else 1), text
    assert "Traceback" not in text
    assert not changes(before, snapshot(tmp_path))
