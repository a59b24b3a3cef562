"""Camera trajectories: object spheres, room coverage (look-at: tests/core/test_cameras.py)."""

from __future__ import annotations

import numpy as np

from regnf.synthetic.trajectories import (
    MIN_EYE_HEIGHT,
    object_capture_poses,
    room_full_coverage_poses,
    room_low_coverage_poses,
)

K = np.array([[240.0, 0.0, 100.0], [0.0, 240.0, 100.0], [0.0, 0.0, 1.0]])


def _project(pose: np.ndarray, K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    cam = (pts - pose[:3, 3]) @ pose[:3, :3]
    return np.c_[cam[:, :2] / cam[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2], cam[:, 2]]


def test_object_poses_surround_and_frame_the_object() -> None:
    centre, radius = np.array([0.0, 0.0, 0.5]), 0.6
    poses = object_capture_poses(centre, radius, 50, K, 200, 200, fill=0.8)
    assert poses.shape == (50, 4, 4)
    offsets = poses[:, :3, 3] - centre
    dist = np.linalg.norm(offsets, axis=1)
    np.testing.assert_allclose(dist, dist[0])
    elev = np.degrees(np.arcsin(offsets[:, 2] / dist))
    assert elev.min() >= -35.0 and elev.max() <= 80.0
    assert elev.min() < -25.0 and elev.max() > 70.0  # seen from below and from above
    azim = np.arctan2(offsets[:, 1], offsets[:, 0])
    assert np.max(np.diff(np.sort(azim))) < np.radians(40)
    # The bounding sphere projects inside the image, spanning about the requested fraction.
    sphere = centre + radius * np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    )
    for pose in poses:
        np.testing.assert_allclose(pose[:3, 2], (centre - pose[:3, 3]) / dist[0])
        uv = _project(pose, K, sphere)
        assert np.all(uv[:, 2] > 0)
        assert np.all((uv[:, :2] > 0) & (uv[:, :2] < 200))


def _room_objects() -> tuple[np.ndarray, np.ndarray]:
    centres = np.array([[-1.5, 1.0, 0.45], [1.2, -0.8, 0.4], [0.5, 1.3, 0.38]])
    return centres, np.array([0.7, 0.8, 0.9])


def _azimuths_seeing(poses: np.ndarray, K: np.ndarray, c: np.ndarray, w: int, h: int) -> np.ndarray:
    seen = []
    for pose in poses:
        u, v, z = _project(pose, K, c[None])[0]
        if z > 0 and 0 <= u < w and 0 <= v < h:
            d = pose[:3, 3] - c
            seen.append(np.arctan2(d[1], d[0]))
    return np.sort(np.array(seen))


def _max_gap(az: np.ndarray) -> float:
    return float(np.max(np.diff(np.r_[az, az[0] + 2 * np.pi]))) if len(az) else 2 * np.pi


def test_room_full_coverage_sees_every_object_from_all_sides() -> None:
    Kr = np.array([[180.0, 0.0, 128.0], [0.0, 180.0, 96.0], [0.0, 0.0, 1.0]])
    centres, radii = _room_objects()
    poses = room_full_coverage_poses((3.0, 2.5), centres, radii, Kr, 256, 192, n=120, seed=3)
    assert poses.shape == (120, 4, 4)
    eyes = poses[:, :3, 3]
    assert np.all(np.abs(eyes[:, 0]) < 3.0) and np.all(np.abs(eyes[:, 1]) < 2.5)
    assert np.all(eyes[:, 2] >= MIN_EYE_HEIGHT)
    for c in centres:
        assert _max_gap(_azimuths_seeing(poses, Kr, c, 256, 192)) < np.radians(100)
    np.testing.assert_array_equal(
        poses, room_full_coverage_poses((3.0, 2.5), centres, radii, Kr, 256, 192, n=120, seed=3)
    )


def test_room_low_coverage_leaves_object_backs_unseen() -> None:
    Kr = np.array([[180.0, 0.0, 128.0], [0.0, 180.0, 96.0], [0.0, 0.0, 1.0]])
    centres, _ = _room_objects()
    poses = room_low_coverage_poses((3.0, 2.5), centres, n=30)
    assert poses.shape == (30, 4, 4)
    eyes = poses[:, :3, 3]
    assert np.all(eyes[:, 1] < 0) and np.all(np.abs(eyes[:, 0]) < 3.0)
    for c in centres:
        az = _azimuths_seeing(poses, Kr, c, 256, 192)
        assert len(az) > 0
        assert _max_gap(az) > np.radians(180)  # at least half the directions never seen
