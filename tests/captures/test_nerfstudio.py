"""nerfstudio transforms.json: poses, depth and intrinsics against the analytic room; detection."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from regnf.captures.formats import detect_format, read_capture
from regnf.captures.model import CaptureError
from regnf.captures.sdfstudio import write_capture
from tests.captures.ns_helpers import (
    CX,
    CY,
    FX,
    FY,
    ROOM,
    H,
    W,
    true_depth,
    truth_poses,
    write_nerfstudio,
)


@pytest.mark.parametrize(("depth_name", "per_frame"), [("png", False), ("npy", True)])
def test_poses_depth_and_intrinsics_match_the_analytic_room(tmp_path: Path, depth_name: str,
                                                            per_frame: bool) -> None:
    write_nerfstudio(tmp_path, depth_name, per_frame_intrinsics=per_frame)
    capture, fmt = read_capture(tmp_path)
    assert fmt == "nerfstudio" and (capture.width, capture.height) == (W, H)
    truth = truth_poses()
    assert len(capture.frames) == len(truth)
    K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    # PNG depth is rounded to the millimetre; .npy float32 to about 1e-7 relative.
    tol = 0.5e-3 + 1e-5 if depth_name == "png" else 1e-5
    for i, pose in enumerate(truth):
        np.testing.assert_allclose(capture.camtoworld_metres(i), pose, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(capture.frames[i].intrinsics, K)
        metres = capture.depth(i).astype(np.float64) * capture.scale
        np.testing.assert_allclose(metres, true_depth(pose), rtol=0, atol=tol)


def test_a_6_by_5_m_room_without_a_scene_box_is_not_cropped(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path)
    capture, _ = read_capture(tmp_path)
    s, c = capture.scale, capture.worldtogt[:3, 3]
    lo, hi = c - s, c + s  # the normalised unit box in metres
    assert np.all(lo <= ROOM[0]) and np.all(hi >= ROOM[1]), (lo, hi)
    # Not a loose guess either: the largest extent (6 m) times the rooms' margin, to the mm.
    assert s == pytest.approx(0.5 * 6.0 * 1.02, abs=2e-3)
    np.testing.assert_allclose(c, ROOM.mean(axis=0), atol=2e-3)


def test_applied_transform_is_kept_and_the_world_is_the_files(tmp_path: Path) -> None:
    applied = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]]
    write_nerfstudio(tmp_path, extra={"applied_transform": applied})
    capture, _ = read_capture(tmp_path)
    assert capture.meta["applied_transform"] == [*applied, [0.0, 0.0, 0.0, 1.0]]
    np.testing.assert_allclose(capture.camtoworld_metres(3), truth_poses()[3], atol=1e-9)


def test_detection_picks_the_format_and_refuses_ambiguity(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path / "ns")
    assert detect_format(tmp_path / "ns").name == "nerfstudio"
    assert detect_format(tmp_path / "ns" / "transforms.json").name == "nerfstudio"
    rgb = [np.zeros((4, 5, 3), np.uint8)]
    write_capture(tmp_path / "sd", rgb, None, np.eye(4)[None], np.diag([5.0, 5.0, 1.0]), np.eye(4))
    assert detect_format(tmp_path / "sd").name == "sdfstudio"
    assert read_capture(tmp_path / "sd")[1] == "sdfstudio"
    (tmp_path / "sd" / "transforms.json").write_text(json.dumps({"frames": []}))
    with pytest.raises(CaptureError, match=r"holds meta_data.json \(sdfstudio\) and transforms.json"):
        read_capture(tmp_path / "sd")
    assert read_capture(tmp_path / "sd", "sdfstudio")[1] == "sdfstudio"
    with pytest.raises(CaptureError, match="not a capture folder: expected one of meta_data.json"):
        read_capture(tmp_path)
