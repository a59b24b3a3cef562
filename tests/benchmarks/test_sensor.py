"""``regnf bench sensor``: which cameras see an object and their error, the widened bars, the
verdicts computed from the rows, its checks before any work, and a tiny-size run end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from regnf.benchmarks import sensor
from regnf.benchmarks.camera_error import cameras_seeing, object_camera_errors, true_camtoworld
from regnf.benchmarks.sensor import bar_columns, object_diagonal, widened_bars
from regnf.benchmarks.sensor_report import summarise
from regnf.captures.instance import Instance, box_corners
from regnf.captures.model import Capture, CaptureFrame
from regnf.cli.app import main
from regnf.registration.metrics import BARS, within_bars
from regnf.synthetic import cache as cache_module
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.sensor_noise import TRUE_POSES_NAME, write_true_poses
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails

SCALE = 2.0  # metres per normalised unit of the hand-made capture


def _look(eye: tuple[float, float, float], forward: tuple[float, float, float]) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) at ``eye`` looking along a horizontal ``forward``."""
    z = np.asarray(forward, dtype=np.float64)
    x = np.cross(z, [0.0, 0.0, 1.0])
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, y, z], axis=1)
    M[:3, 3] = eye
    return M


def _capture(root: Path, noisy: bool) -> tuple[Capture, np.ndarray]:
    """A capture written by hand: a 1 m cube at y in [2.5, 3.5] m and six cameras at the origin.

    Every depth image is constant (what a wall at that distance gives). Frame 0 looks at the
    cube and measures its front face (2.5 m); 1 measures a wall behind it (6 m); 2 an occluder
    in front (1 m); 3 looks away; 4 has no return anywhere; 5 sees the cube but is held out.
    The stored poses are the true ones, but frame 0's is off by 1 cm and 0.2 degrees.
    """
    w, h = 40, 30
    K = np.array([[20.0, 0.0, 20.0], [0.0, 20.0, 15.0], [0.0, 0.0, 1.0]])
    eye = (0.0, 0.0, 0.5)
    true = np.stack([_look(eye, (0, 1, 0))] * 3 + [_look(eye, (0, -1, 0)), _look(eye, (0, 1, 0)),
                                                   _look(eye, (0, 1, 0))])
    stored = true.copy()
    turn = math.radians(0.2)
    stored[0, :3, :3] = np.array([[math.cos(turn), -math.sin(turn), 0], [math.sin(turn), math.cos(turn), 0],
                                  [0, 0, 1]]) @ true[0, :3, :3]
    stored[0, :3, 3] += [0.01, 0.0, 0.0]
    frames = []
    for i, metres in enumerate((2.5, 6.0, 1.0, 2.5, 0.0, 2.5)):
        path = root / f"depth_{i}.npy"
        np.save(path, np.full((h, w), metres / SCALE, dtype=np.float32))  # stored in normalised units
        pose = stored[i].copy()
        pose[:3, 3] /= SCALE
        frames.append(CaptureFrame(rgb_path=root / f"rgb_{i}.png", depth_path=path, camtoworld=pose,
                                   intrinsics=K, split="test" if i == 5 else "train"))
    worldtogt = np.diag([SCALE, SCALE, SCALE, 1.0])
    cube = Instance(id="t_0", library="t", label="table", object_to_world=np.eye(4),
                    box_corners=box_corners(np.array([[-0.5, 2.5, 0.0], [0.5, 3.5, 1.0]]), np.eye(4)))
    meta = {"noise": {"level": "slam"}} if noisy else {}
    capture = Capture(root=root, width=w, height=h, frames=frames, worldtogt=worldtogt,
                      scene_box={"aabb": np.array([[-5.0, -5, -5], [5, 5, 5]]), "near": 0.01, "far": 10.0},
                      instances=[cube], meta=meta)
    if noisy:
        write_true_poses(root, true, "slam", 0)
    return capture, true


def test_a_camera_sees_an_object_where_its_depth_lands_in_the_box(tmp_path: Path) -> None:
    capture, true = _capture(tmp_path, noisy=True)
    np.testing.assert_allclose(true_camtoworld(capture), true, atol=1e-12)
    seen = cameras_seeing(capture, true, capture.train_indices(), capture.instances)
    assert seen[:, 0].tolist() == [True, False, False, False, False]
    errors = object_camera_errors(capture)
    assert errors["t_0"]["cameras"] == 1
    assert errors["t_0"]["position_cm"] == pytest.approx(1.0, abs=1e-9)
    assert errors["t_0"]["rotation_deg"] == pytest.approx(0.2, abs=1e-9)


def test_an_ideal_capture_has_exact_cameras_and_a_noisy_one_needs_its_true_poses(tmp_path: Path) -> None:
    (tmp_path / "ideal").mkdir()
    ideal, _ = _capture(tmp_path / "ideal", noisy=False)
    assert object_camera_errors(ideal)["t_0"] == {"cameras": 1, "position_cm": 0.0, "rotation_deg": 0.0}
    (tmp_path / "noisy").mkdir()
    noisy, _ = _capture(tmp_path / "noisy", noisy=True)
    (tmp_path / "noisy" / TRUE_POSES_NAME).unlink()
    with pytest.raises(ValueError, match=f"{TRUE_POSES_NAME}: no such true-pose file"):
        object_camera_errors(noisy)
    write_true_poses(tmp_path / "noisy", np.stack([np.eye(4)] * 2), "slam", 0)
    with pytest.raises(ValueError, match=r"expected 6 \(4, 4\) poses"):
        object_camera_errors(noisy)


def test_the_widened_bars_add_the_cameras_error_to_the_plain_ones() -> None:
    bars = widened_bars(position_cm=0.5, rotation_deg=0.3, diagonal_m=1.25)
    assert bars == pytest.approx({"rot_geodesic_sym_rad": 0.02 + 0.3 * math.pi / 180,
                                  "trans_rel_diag_sym": 0.01 + 0.005 / 1.25, "scale_rel": 0.01})
    assert widened_bars(None, None, 1.0) == BARS  # an object no camera sees keeps the plain bars


# ----------------------------------------------------------------------------- verdicts

GOOD = {"rot_geodesic_sym_rad": 0.004, "trans_rel_diag_sym": 0.002, "scale_rel": 0.003}
SLAM_CAMERA = {"cameras": 40, "position_cm": 0.6, "rotation_deg": 0.2}
ROOM_OBJECTS = (("ac-room", "dc"), ("ac-room", "fc"), ("atbl-room", "t"))


def _right(level: str, scene: str, obj: str, accepted: bool = True, camera: dict = SLAM_CAMERA,
           confidence: float = 0.9, **errors: float) -> dict:
    row = {"level": level, "coverage": "low", "scene": scene, "object": obj, "box_object": obj, "method": "regnf",
           "views": "multi", "library_source": "mesh", "wrong_pair": False, "accepted": accepted,
           "confidence": confidence, "difference_observed": None, "seconds": 1.0, **GOOD, **errors}
    return {**row, **bar_columns(row, camera, object_diagonal(obj))}


def _wrong(level: str, scene: str, obj: str, box: str, accepted: bool, confidence: float,
           difference: float = 0.9) -> dict:
    return {"level": level, "coverage": "low", "scene": scene, "object": obj, "box_object": box, "method": "regnf",
            "views": "multi", "library_source": "mesh", "wrong_pair": True, "accepted": accepted,
            "confidence": confidence, "difference_observed": difference, "seconds": 1.0,
            **dict.fromkeys(GOOD), "cameras": None, "camera_position_cm": None, "camera_rotation_deg": None,
            "bars_widened": None, "within_bars": None, "within_widened_bars": None}


def _room(level: str, scene: str, true: int, within: int, false: int = 0) -> dict:
    return {"level": level, "coverage": "low", "scene": scene,
            "discovery": {"true_instances": true, "found": true, "identified": within, "within_bars": within,
                          "false_instances": false}}


def _checks(summary: dict) -> dict[str, bool]:
    return {c["check"]: c["pass"] for c in summary["checks"]}


def test_a_pair_within_the_widened_bars_only_passes_slam_but_not_sensor() -> None:
    # 1.2 % of dc's diagonal: outside the plain 1 %, inside 1 % + 0.6 cm / diagonal.
    assert 0.012 < 0.01 + 0.006 / object_diagonal("dc")
    for level, verdict in (("sensor", "fail"), ("slam", "pass"), ("harsh", "pass")):
        rows = [_right(level, s, o) for s, o in ROOM_OBJECTS[1:]] + [_right(level, "ac-room", "dc",
                                                                            trans_rel_diag_sym=0.012)]
        s = summarise(rows, [], level, "low")
        assert (s["pairs"], s["accepted"], s["within_bars"], s["within_widened_bars"]) == (3, 3, 2, 3)
        assert s["accepted_outside_widened_bars"] == 0 and s["verdict"] == verdict, s["checks"]
    # Outside the widened bars too: accepted, it fails every level; rejected, only those that ask for 3/3.
    for accepted, verdicts in ((True, ("fail", "fail", "fail")), (False, ("fail", "fail", "pass"))):
        for level, verdict in zip(("sensor", "slam", "harsh"), verdicts):
            rows = [_right(level, s, o) for s, o in ROOM_OBJECTS[1:]] + [
                _right(level, "ac-room", "dc", accepted=accepted, scale_rel=0.011)]
            s = summarise(rows, [], level, "low")
            assert s["accepted_outside_widened_bars"] == int(accepted)
            assert _checks(s)["accepted outside the widened bars"] is (not accepted)
            assert s["verdict"] == verdict, (level, accepted, s["checks"])


def test_a_wrong_object_accepted_fails_every_level_unless_it_loses_to_the_right_one_or_is_unobservable() -> None:
    right = [_right("harsh", s, o, confidence=0.8) for s, o in ROOM_OBJECTS]
    cases = [
        ([_wrong("harsh", "ac-room", "t", "dc", False, 0.5)], 0, "pass"),       # rejected
        ([_wrong("harsh", "ac-room", "t", "dc", True, 0.6)], 1, "fail"),        # a table in a chair's box
        ([_wrong("harsh", "ac-room", "c", "dc", True, 0.7)], 0, "pass"),        # a chair below the right one
        ([_wrong("harsh", "ac-room", "c", "dc", True, 0.85)], 1, "fail"),       # above it, difference observed
        ([_wrong("harsh", "ac-room", "fc-nop", "fc", True, 0.85, 0.01)], 0, "pass"),  # difference never observed
    ]
    for wrong, bad, verdict in cases:
        s = summarise(right + wrong, [], "harsh", "low")
        assert s["wrong_pairs"] == 1 and s["wrong_accepted"] == int(wrong[0]["accepted"])
        assert s["wrong_objects_accepted"] == bad and s["verdict"] == verdict, wrong
    assert summarise(right + cases[-1][0], [], "harsh", "low")["wrong_unobserved"] == 1
    assert "wrong objects accepted" not in _checks(summarise(right, [], "harsh", "low"))  # not run: no check


def test_discovery_must_place_all_but_one_instance_with_no_false_one_at_the_sensor_level() -> None:
    rows = [_right("sensor", s, o) for s, o in ROOM_OBJECTS]
    for rooms, verdict in (([_room("sensor", "ac-room", 5, 5), _room("sensor", "mix-room", 6, 5)], "pass"),
                           ([_room("sensor", "ac-room", 5, 4), _room("sensor", "mix-room", 6, 5)], "fail"),
                           ([_room("sensor", "ac-room", 5, 5), _room("sensor", "mix-room", 6, 6, false=1)], "fail")):
        s = summarise(rows, rooms, "sensor", "low")
        assert s["discovery"]["true_instances"] == 11 and s["verdict"] == verdict, s["checks"]
    # slam asks nothing of discovery; rows of another level or coverage are not counted.
    slam = summarise([_right("slam", s, o) for s, o in ROOM_OBJECTS], [_room("slam", "ac-room", 5, 0)], "slam", "low")
    assert slam["verdict"] == "pass" and slam["discovery"]["within_bars"] == 0
    assert summarise(rows + [_right("slam", "ac-room", "dc", accepted=False)], [], "sensor", "low")["pairs"] == 3


# ----------------------------------------------------------------------------- the command


def test_a_selection_the_benchmark_lacks_is_refused_before_any_work(tmp_path: Path, capsys) -> None:
    before = snapshot(tmp_path)
    out = tmp_path / "s.json"
    line = assert_fails(capsys, ["bench", "sensor", "--json", str(out), "--rooms", "atbl-room", "--objects", "dc",
                                 "--cache-dir", str(tmp_path / "cache")], "--objects dc: no pair of the rooms")
    assert "choose from et t wt" in line
    assert changes(before, snapshot(tmp_path)) == []


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str, Path]:
    """The benchmark at the tiny size: the mix-room's table at low coverage, ideal and sensor,
    one wrong pair (a chair in the table's box), no discovery, every field trained 20 steps."""
    root = tmp_path_factory.mktemp("sensor")
    out, md = root / "s.json", root / "s.md"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sensor, "wrong_pairs", lambda room: [("dc", "t")])
        mp.setattr(cache_module, "TINY_STEPS", 20)
        rc = main(["bench", "sensor", "--size", "tiny", "--levels", "ideal", "sensor", "--coverages", "low",
                   "--rooms", "mix-room", "--objects", "t", "--no-discovery", "--noise-seed", "3",
                   "--json", str(out), "--markdown", str(md), "--cache-dir", str(root / "cache")])
    assert rc == 0
    return json.loads(out.read_text()), md.read_text(), root / "cache"


def test_a_tiny_run_gives_every_row_and_verdicts_computed_from_them(tiny_run) -> None:
    result, table, cache_dir = tiny_run
    assert result["meta"]["size"] == "tiny" and "--noise-seed 3" in result["meta"]["command"]
    rooms = result["rooms"]
    assert [(r["level"], r["noise_seed"], r["scene"], r["coverage"]) for r in rooms] == [
        ("ideal", 0, "mix-room", "low"), ("sensor", 3, "mix-room", "low")]
    for r in rooms:
        assert r["discovery"] is None and r["discovery_seconds"] is None
        assert 0 < r["surface_error_mean_rel"] < r["surface_error_p95_rel"] and r["train_seconds"] > 0
    pairs = result["pairs"]
    assert [(p["level"], p["object"], p["box_object"], p["wrong_pair"]) for p in pairs] == [
        ("ideal", "t", "t", False), ("ideal", "dc", "t", True), ("sensor", "t", "t", False),
        ("sensor", "dc", "t", True)]
    for p in pairs:
        assert p["library_source"] == "mesh" and p["coverage"] == "low" and isinstance(p["accepted"], bool)
        assert not any(k.startswith("_") for k in p)
        if p["wrong_pair"]:
            assert p["bars_widened"] is None and p["rot_geodesic_sym_rad"] is None
            continue
        assert p["cameras"] > 0 and p["within_bars"] == within_bars(p)
        assert p["within_widened_bars"] == within_bars(p, p["bars_widened"])
    ideal, noisy = pairs[0], pairs[2]
    assert ideal["camera_position_cm"] == 0 and ideal["bars_widened"] == BARS
    # The sensor level's pose jitter is 1 mm / 0.05 degree.
    assert 0.01 < noisy["camera_position_cm"] < 0.5 and 0.005 < noisy["camera_rotation_deg"] < 0.2
    assert result["summary"] == [summarise(pairs, rooms, lv, "low") for lv in ("ideal", "sensor")]
    for lv in ("ideal", "sensor"):
        assert f"| {lv} | low | 1 |" in table
    assert table.index("| mix-room | t | low | ideal |") < table.index("| mix-room | t | low | sensor |")
    # The ideal level is the capture and the field every other benchmark uses (their keys unchanged).
    cache = Cache(cache_dir, progress=False, size="tiny")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cache_module, "TINY_STEPS", 20)
        assert rooms[0]["checkpoint"] == str(cache.scene_field("mix-room", "low"))
    noisy_capture = cache.room_capture("mix-room", RoomCaptureConfig(coverage="low", noise="sensor", noise_seed=3))
    assert (noisy_capture.root / TRUE_POSES_NAME).is_file()
