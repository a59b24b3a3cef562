"""A nerfstudio capture written by test code (numpy + imageio): an empty box room in metres.

The room is ``ROOM`` (6 m x 5 m x 3 m, off the origin); each camera stands inside it, so every
pixel's ray hits a wall, the floor or the ceiling, and its exact z-depth is a ray-box exit.
Poses are written as nerfstudio does: camera-to-world with OpenGL camera axes.
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np

ROOM = np.array([[1.0, -2.0, 0.0], [7.0, 3.0, 3.0]])
"""(2, 3) min and max corner of the room, metres."""
W, H = 40, 30
"""Image size, pixels."""
FX, FY, CX, CY = 20.0, 21.0, 19.5, 15.25
"""Intrinsics, pixels (pixel centres at u + 0.5)."""


def opencv_pose(yaw: float, pitch: float, centre: np.ndarray) -> np.ndarray:
    """(4, 4) OpenCV camera-to-world looking along (yaw about +Z, pitch up), Z up."""
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)  # down
    out = np.eye(4)
    out[:3, :3] = np.stack([x, y, f], axis=1)
    out[:3, 3] = centre
    return out


def true_depth(pose: np.ndarray) -> np.ndarray:
    """(H, W) exact z-depth in metres of the room's inside seen from ``pose`` (OpenCV)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([(u - CX) / FX, (v - CY) / FY, np.ones_like(u)], axis=-1)  # z = 1
    d = rays @ pose[:3, :3].T
    o = pose[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (ROOM[1] - o) / d, (ROOM[0] - o) / d)
    t[~np.isfinite(t)] = np.inf
    return t.min(axis=-1)  # rays have unit z in the camera, so t is z-depth


def truth_poses() -> np.ndarray:
    """(n, 4, 4) OpenCV camera-to-world of the frames, metres."""
    centre = np.array([4.2, 0.3, 1.4])
    poses = [opencv_pose(k * np.pi / 4, 0.1 * (k % 3 - 1), centre + [0.1 * k, 0.0, 0.0]) for k in range(8)]
    return np.stack(poses)


def write_nerfstudio(root: Path, depth_name: str = "png", unit: float | None = None,
                     per_frame_intrinsics: bool = False, extra: dict | None = None) -> dict:
    """Write the room capture to ``root``; returns the JSON written.

    ``depth_name``: ``png`` (uint16 millimetres, or ``unit`` metres per count) or ``npy``
    (float32 metres).
    """
    root.mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    frames = []
    rng = np.random.default_rng(0)
    for i, pose in enumerate(truth_poses()):
        rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        iio.imwrite(root / "images" / f"frame_{i:05d}.png", rgb)
        depth = true_depth(pose)
        if depth_name == "png":
            counts = np.round(depth / (unit or 1e-3)).astype(np.uint16)
            iio.imwrite(root / "depth" / f"frame_{i:05d}.png", counts)
            dpath = f"depth/frame_{i:05d}.png"
        else:
            np.save(root / "depth" / f"frame_{i:05d}.npy", depth.astype(np.float32))
            dpath = f"depth/frame_{i:05d}.npy"
        gl = pose @ np.diag([1.0, -1.0, -1.0, 1.0])
        frame = {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": gl.tolist(),
                 "depth_file_path": dpath}
        if per_frame_intrinsics:
            frame.update(fl_x=FX, fl_y=FY, cx=CX, cy=CY, w=W, h=H)
        frames.append(frame)
    data: dict = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}
    if not per_frame_intrinsics:
        data.update(fl_x=FX, fl_y=FY, cx=CX, cy=CY, w=W, h=H)
    if unit is not None:
        data["depth_unit_scale_factor"] = unit
    data.update(extra or {})
    (root / "transforms.json").write_text(json.dumps(data))
    return data
