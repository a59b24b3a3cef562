"""Scene or object: from a capture's metadata, else from where its cameras stand."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regnf.captures.formats import read_capture
from regnf.captures.model import Capture
from regnf.captures.scene_kind import SceneKind, scene_kind
from regnf.captures.survey import depth_cloud, metric_poses, survey_frames
from tests.captures.ns_helpers import write_nerfstudio
from tests.captures.sphere_helpers import write_sphere_capture


def kind_of(capture: Capture) -> SceneKind:
    poses = metric_poses(capture)
    return scene_kind(capture, poses[:, :3, 3], depth_cloud(capture, survey_frames(capture), poses))


def test_cameras_inside_a_room_make_a_scene(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path / "ns")
    kind = kind_of(read_capture(tmp_path / "ns")[0])
    assert kind.kind == "scene"
    assert kind.reason == "cameras inside the observed space: 8 of 8 camera centres inside the box of the depth points"


def test_cameras_around_an_object_make_an_object(tmp_path: Path) -> None:
    kind = kind_of(write_sphere_capture(tmp_path / "sphere"))
    assert kind.kind == "object"
    assert kind.reason.startswith("cameras outside the observed space, looking in: 0 of 12 camera centres")


def test_the_metadata_says_which_without_depth(tmp_path: Path) -> None:
    capture = write_sphere_capture(tmp_path / "sphere", meta={"zero_depth": "empty", "kind": "scene"})
    kind = scene_kind(capture, np.zeros((1, 3)), np.zeros((0, 3)))
    assert kind == ("scene", "a room: the capture's metadata says kind 'scene'")
    capture.meta["kind"] = "object"
    assert scene_kind(capture, np.zeros((1, 3)), np.zeros((0, 3))).kind == "object"
