"""A hostile capture and a careless user against ``regnf discover``: a candidate that cannot be
registered, the scene and the library swapped, files of the user's in the output folder.

A candidate that fails on its input is skipped with its reason, and the run goes on (exit 0);
a room given as a library object is refused from the checkpoints' headers before anything is
loaded (exit 1, nothing on disk changed); a rerun removes only the files its previous run
recorded.

Checkpoint loading is replaced by exact analytic fields where discovery runs (as in
``tests/cli/test_cli_discover.py``); the checkpoints on disk are tiny real ones whose
headers carry the labels.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import regnf.cli.commands_discover as commands
from regnf.fields.analytic import Box as BoxField
from regnf.fields.analytic import Cylinder, Transformed, Union
from regnf.fields.oriented_box import OrientedBox
from regnf.registration import discovery
from regnf.registration.candidates import Candidate, Candidates
from regnf.registration.discovery import Discovery, DiscoveryResult, Tried
from regnf.registration.result import RegistrationResult
from regnf.registration.sampling import SurfaceSamples
from regnf.registration.step_failures import StepFailed, attempt
from regnf.registration.transform import SimilarityTransform
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails, run_cli
from tests.registration.fixtures import make_object, placement
from tests.scene_graph.helpers import checkpoint

CHAIR_TO_SCENE = placement([0, 0, 1], 0.7, [1.0, -0.5, 0.0], 1.0)
LAMP_XY = np.array([-1.0, 1.2])
# One process (the analytic fields patched in are not what workers would load), one library
# object, a short initialisation and no refit: the chair of the exact field is found all the same.
FAST = ["--discovery.candidates.resolution", "128", "--discovery.shortlist", "1", "--discovery.workers", "1",
        "--discovery.no-refit-box", "--discovery.registration.no-upright",
        "--discovery.registration.init.ransac-runs", "1", "--discovery.registration.init.candidates", "4"]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Tiny checkpoints: a room (label scene), a chair and a table (their classes)."""
    src = tmp_path_factory.mktemp("discover_src")
    return {"room": checkpoint(src, "room", "scene", scale=3.0), "c": checkpoint(src, "c", "chair", seed=1),
            "t": checkpoint(src, "t", "table", seed=2)}


@pytest.fixture()
def analytic(files: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """Each checkpoint loads as an analytic field: a room with the chair and a lamp, the chair."""
    chair = make_object()
    chair.info.name = "c"
    room = Union(BoxField((3.0, 3.0, 0.05), (0.0, 0.0, -0.05)), Transformed(make_object(), CHAIR_TO_SCENE),
                 Cylinder(0.12, 0.7, (*LAMP_XY, 0.7)), label="scene", name="room")
    table = Union(BoxField((0.4, 0.4, 0.03), (0.0, 0.0, 0.72)), Cylinder(0.06, 0.35, (0.0, 0.0, 0.35)),
                  label="table", name="t")
    fields = {str(files["room"]): room, str(files["c"]): chair, str(files["t"]): table}
    monkeypatch.setattr(commands, "load_field", lambda path, device="cpu": fields[str(path)])
    return files


def _args(files: dict[str, Path], out: Path, scene: str = "room", library: tuple[str, ...] = ("c",)) -> list[str]:
    return ["discover", "--scene", str(files[scene]), "--library", *(str(files[n]) for n in library),
            "--out", str(out), *FAST]


def _lamp_box_sees_nine_points(monkeypatch: pytest.MonkeyPatch) -> None:
    """The scene sampled in the lamp's box holds 9 points, as a noisy capture's box can."""
    real = discovery.sample_surface

    def sample(field, box=None, config=None, side="scene", device=None) -> SurfaceSamples:
        got = real(field, box, config, side=side, device=device)
        if side == "scene" and np.linalg.norm(box.center[:2] - LAMP_XY) < 0.3:  # analytic: field frame = metres
            return SurfaceSamples(got.points[:9], got.normals[:9], got.view_ids[:9])
        return got

    monkeypatch.setattr(discovery, "sample_surface", sample)


def test_a_candidate_with_too_few_samples_is_skipped_and_the_others_are_found(analytic, tmp_path, capsys,
                                                                             monkeypatch) -> None:
    _lamp_box_sees_nine_points(monkeypatch)
    out = tmp_path / "out"
    status, err = run_cli(capsys, _args(analytic, out))
    text = " ".join(err.split())
    assert status == 0, err
    assert "discovered 1 instances in 2 candidates, 1 skipped" in text
    assert ("skipped: ranking the library in its box: RegnfError: scene samples: 9 points are too few to "
            "register (need >= 10)") in text
    saved = json.loads((out / "discovery.json").read_text())
    skipped, = saved["skipped"]
    assert skipped["reason"].endswith("RegnfError: scene samples: 9 points are too few to register (need >= 10)")
    np.testing.assert_allclose(skipped["box_metres"]["center"][:2], LAMP_XY, atol=0.05)
    record = saved["candidates"][skipped["candidate"]]
    assert record["chosen"] is None and record["tried"] == [] and record["skipped"] == skipped["reason"]
    found = [c for c in saved["candidates"] if c["chosen"] is not None]
    assert [c["chosen"] for c in found] == ["c"]
    assert saved["files"] == [f"registration/candidate_{found[0]['candidate']}.json"]
    assert sorted(p.name for p in (out / "registration").iterdir()) == [f"candidate_{found[0]['candidate']}.json"]


def test_a_shortlisted_object_whose_registration_fails_is_left_out_with_its_reason() -> None:
    from regnf.registration.discovery import Ranking, choose

    box = OrientedBox.from_aabb(np.zeros(3), np.ones(3))
    empty = SurfaceSamples(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    ranking = Ranking(box, empty, {"a": 0.9, "b": 0.8}, 0.0)
    good = RegistrationResult(SimilarityTransform.from_matrix(np.eye(4)), 0.9, True, "regnf")
    def degenerate() -> None:
        raise ValueError("a sample cloud has zero spread\n(all points coincide)")

    failed = attempt(degenerate)
    assert failed == StepFailed("ValueError: a sample cloud has zero spread")
    cand = Candidate(box, np.zeros((1, 3)))
    d = choose(cand, ranking, {"a": failed, "b": good}, BoxField((1.0, 1.0, 1.0)), {}, {},
               discovery.DiscoveryConfig(refit_box=False))
    assert d.chosen is not None and d.chosen.library_name == "b"
    assert d.tried[0] == Tried("a", 0.9, None, "ValueError: a sample cloud has zero spread")
    # A bug is not a failure of the input: it still ends the run.
    with pytest.raises(KeyError):
        attempt(lambda: {}["x"])


@pytest.mark.parametrize(("scene", "library", "pattern"), [
    ("c", ("room",), (r"--library \S+room\.safetensors: is a scene field \(label 'scene'\), not a library object; "
                      r"are --scene and --library swapped\?$")),
    ("room", ("c", "room"), (r"--library \S+room\.safetensors: is a scene field \(label 'scene'\), not a library "
                             r"object$")),
    ("t", ("c",), r"--scene \S+t\.safetensors: is a library object's field \(label 'table'\), not a scene field"),
])
def test_a_room_as_library_object_or_an_object_as_scene_is_refused_before_loading(
        files, tmp_path, capsys, monkeypatch, scene, library, pattern) -> None:
    def no_loading(path, device="cpu"):
        raise AssertionError(f"{path} was loaded")

    monkeypatch.setattr(commands, "load_field", no_loading)
    before = snapshot(tmp_path), snapshot(files["room"].parent)
    line = assert_fails(capsys, _args(files, tmp_path / "out", scene, library), pattern)
    assert line.startswith("regnf discover: ")
    assert not changes(before[0], snapshot(tmp_path)) and not changes(before[1], snapshot(files["room"].parent))


def test_register_refuses_the_scene_and_the_library_swapped(files, tmp_path, capsys, monkeypatch) -> None:
    import regnf.cli.commands_registration as register_command

    chair, room = make_object(), Union(BoxField((3.0, 3.0, 0.05), (0.0, 0.0, -0.05)), label="scene")
    fields = {str(files["c"]): chair, str(files["room"]): room}
    monkeypatch.setattr(register_command, "load_field", lambda path, device="cpu": fields[str(path)])
    (tmp_path / "box.json").write_text(json.dumps({"center": [0, 0, 0.4], "size": [1, 1, 0.8]}))
    before = snapshot(tmp_path)
    assert_fails(capsys, ["register", "--scene", str(files["c"]), "--library", str(files["room"]),
                          "--box", str(tmp_path / "box.json"), "--out", str(tmp_path / "r.json")],
                 r"--library \S+room\.safetensors: is a scene field .* are --scene and --library swapped\?$")
    assert not changes(before, snapshot(tmp_path))


def _result(indices: list[int], scene) -> DiscoveryResult:
    """A discovery that identified candidates ``indices`` of three (the chair, as registered)."""
    truth = SimilarityTransform.from_matrix(np.linalg.inv(CHAIR_TO_SCENE))
    out = []
    for k in range(3):
        box = OrientedBox.from_aabb(np.array([k, 0.0, 0.0]), np.array([k + 0.5, 0.5, 0.8]))
        cand = Candidate(box, np.random.default_rng(k).uniform([k, 0, 0], [k + 0.5, 0.5, 0.8], (50, 3)))
        chosen = Tried("c", 0.9, RegistrationResult(truth, 0.9, True, "regnf")) if k in indices else None
        out.append(Discovery(cand, discovery.proposal_of(cand, scene), [] if chosen is None else [chosen], chosen))
    return DiscoveryResult(out, Candidates([d.candidate for d in out], [], 150), {"total": 1.0})


def test_a_rerun_removes_only_the_files_its_previous_run_recorded(analytic, tmp_path, capsys, monkeypatch) -> None:
    runs = iter([[0, 1, 2], [1]])
    monkeypatch.setattr(discovery, "discover", lambda scene, *a, **k: _result(next(runs), scene))
    out = tmp_path / "out"
    assert run_cli(capsys, _args(analytic, out))[0] == 0
    first = json.loads((out / "discovery.json").read_text())["files"]
    assert first == [f"registration/candidate_{k}.json" for k in range(3)]
    assert all((out / f).is_file() for f in first)
    (out / "registration" / "notes.txt").write_text("mine")  # the user's, added after the first run
    (out / "registration" / "candidate_7.json").write_text("{}")  # named like ours, never recorded
    status, err = run_cli(capsys, _args(analytic, out))
    assert status == 0, err
    assert json.loads((out / "discovery.json").read_text())["files"] == ["registration/candidate_1.json"]
    assert sorted(p.name for p in (out / "registration").iterdir()) == ["candidate_1.json", "candidate_7.json",
                                                                         "notes.txt"]
    assert (out / "registration" / "notes.txt").read_text() == "mine"
