"""An sdfstudio capture in metres that states no ``worldtogt`` and no scene box is normalised
from its cameras and depth, never cropped to the unit cube: the 6 m x 5 m room of
``ns_helpers``, written here by test code as a bare ``meta_data.json`` with float depth in metres.
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.captures.sdfstudio import load_capture
from regnf.training.training import train_rgbd
from tests.captures.ns_helpers import CX, CY, FX, FY, ROOM, H, W, true_depth, truth_poses
from tests.captures.test_field_agreement import CONFIG


def _write_bare_sdfstudio(root: Path, poses: np.ndarray) -> None:
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    frames = []
    for i, pose in enumerate(poses):
        iio.imwrite(root / f"{i:03d}_rgb.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        np.save(root / f"{i:03d}_depth.npy", true_depth(pose).astype(np.float32))
        K = [[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]]
        frames.append({"rgb_path": f"{i:03d}_rgb.png", "sensor_depth_path": f"{i:03d}_depth.npy",
                       "camtoworld": pose.tolist(), "intrinsics": K})
    meta = {"camera_model": "OPENCV", "height": H, "width": W, "frames": frames}
    (root / "meta_data.json").write_text(json.dumps(meta))


def test_a_metric_room_without_a_box_is_normalised_not_cropped(tmp_path: Path) -> None:
    poses = truth_poses()
    _write_bare_sdfstudio(tmp_path, poses)
    capture = load_capture(tmp_path)
    assert capture.scale == pytest.approx(0.5 * 6.0 * 1.02, abs=2e-3)
    for i, pose in enumerate(poses):
        np.testing.assert_allclose(capture.camtoworld_metres(i), pose, rtol=0, atol=1e-9)
        np.testing.assert_allclose(capture.depth(i) * capture.scale, true_depth(pose), rtol=0, atol=1e-5)
    # Trained, the field's bounds (in metres) hold every wall point the frames saw: cropped to a
    # 2 m cube in metres they would end at x = 1 m, and the room spans x = 1..7 m.
    field, _ = train_rgbd(capture, CONFIG, progress=False)
    to_world = field.to_world.detach().double().numpy()
    corners = field.bounds.detach().double().numpy() * to_world[0, 0] + to_world[:3, 3]
    pixels = np.stack(np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5), -1).reshape(-1, 2)
    seen = (pixels - [CX, CY]) / [FX, FY]
    for pose in poses:
        z = true_depth(pose).reshape(-1, 1)
        cam = np.concatenate([seen * z, z], axis=1)
        pts = cam @ pose[:3, :3].T + pose[:3, 3]
        assert np.all(pts >= corners[0] - 1e-6) and np.all(pts <= corners[1] + 1e-6)
    assert corners[1, 0] - corners[0, 0] >= ROOM[1, 0] - ROOM[0, 0]


def test_a_normalised_capture_without_a_box_is_taken_as_it_stands(tmp_path: Path) -> None:
    # The same room shrunk into the unit box: nothing to normalise, the identity is kept.
    poses = truth_poses().copy()
    _write_bare_sdfstudio(tmp_path, poses)
    capture = load_capture(tmp_path)
    assert capture.scale != 1.0
    small = tmp_path / "small"
    small.mkdir()
    meta = json.loads((tmp_path / "meta_data.json").read_text())
    s, c = capture.scale, capture.worldtogt[:3, 3]
    for i, f in enumerate(meta["frames"]):
        pose = np.asarray(f["camtoworld"])
        pose[:3, 3] = (pose[:3, 3] - c) / s
        f["camtoworld"] = pose.tolist()
        np.save(small / f"{i:03d}_depth.npy", (true_depth(poses[i]) / s).astype(np.float32))
        (small / f"{i:03d}_rgb.png").write_bytes((tmp_path / f"{i:03d}_rgb.png").read_bytes())
    (small / "meta_data.json").write_text(json.dumps(meta))
    again = load_capture(small)
    np.testing.assert_array_equal(again.worldtogt, np.eye(4))
    np.testing.assert_array_equal(again.scene_box["aabb"], [[-1.0] * 3, [1.0] * 3])
