"""A ScanNet export written by test code (numpy + imageio): an empty box room in metres, Z up.

The room is ``ROOM`` (4 m x 3 m x 2.5 m, off the origin), seen from inside, so every ray exits
through a wall, the floor or the ceiling and its exact z-depth is a ray-box exit. Each of the six
faces has its own colour (``FACE_COLOURS``). Depth is 64x48 uint16 millimetres; colour is
128x96 with intrinsics of its own (not a plain 2x scaling of the depth's), as SensReader writes
them. Frame ``BAD_FRAME`` has a ``-inf`` pose, as ScanNet writes a frame whose tracking was lost.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tests.captures.ns_helpers import opencv_pose

ROOM = np.array([[0.5, -1.0, 0.0], [4.5, 2.0, 2.5]])
"""(2, 3) min and max corner of the room, metres."""
DIAG = float(np.linalg.norm(ROOM[1] - ROOM[0]))
"""Diagonal of the room, metres."""
W, H = 64, 48
"""Depth image size, pixels."""
K_DEPTH = np.array([[50.0, 0.0, 31.7], [0.0, 51.0, 24.2], [0.0, 0.0, 1.0]])
"""Depth intrinsics (pixel centres at u + 0.5)."""
CW, CH = 128, 96
"""Colour image size, pixels."""
K_COLOUR = np.array([[97.0, 0.0, 61.3], [0.0, 99.0, 45.8], [0.0, 0.0, 1.0]])
"""Colour intrinsics: a wider view than the depth's, principal point off the 2x scaling's."""
FACE_COLOURS = np.array([[200, 30, 30], [30, 200, 30], [30, 30, 200], [200, 200, 30], [30, 200, 200],
                         [200, 30, 200]], dtype=np.uint8)
"""Colour of the faces x-min, y-min, z-min (floor), x-max, y-max, z-max (ceiling)."""
N_FRAMES = 12
"""Frames written, ids 0..11 (so that numerical and lexical order differ)."""
BAD_FRAME = 5
"""The frame whose pose is written as -inf."""


def truth_poses() -> np.ndarray:
    """(N_FRAMES, 4, 4) OpenCV camera-to-world of frames 0..11, metres (frame BAD_FRAME's is written -inf)."""
    centre = np.array([2.4, 0.6, 1.3])
    return np.stack([
        opencv_pose(k * np.pi / 6, 0.15 * (k % 3 - 1), centre + [0.08 * (k % 4), -0.05 * (k % 3), 0.02 * k])
        for k in range(N_FRAMES)
    ])


def trace(pose: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact z-depth (metres) and face index of every pixel of a view of the room's inside.

    Returns
    -------
    (height, width) float64 and (height, width) int
        Depth, and the face hit: 0-2 the min faces along x, y, z; 3-5 the max faces.
    """
    v, u = np.mgrid[0:height, 0:width] + 0.5
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # z = 1
    d = rays @ pose[:3, :3].T
    o = pose[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (ROOM[1] - o) / d, (ROOM[0] - o) / d)
    t[~np.isfinite(t)] = np.inf
    axis = t.argmin(axis=-1)
    face = axis + 3 * (np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0)
    return t.min(axis=-1), face  # rays have unit z in the camera, so t is z-depth


def true_depth(pose: np.ndarray) -> np.ndarray:
    """(H, W) exact z-depth in metres on the depth grid."""
    return trace(pose, K_DEPTH, W, H)[0]


def depth_mm(pose: np.ndarray) -> np.ndarray:
    """(H, W) uint16 depth in millimetres, as the sensor file holds it."""
    return np.round(true_depth(pose) * 1000.0).astype(np.uint16)


def colour_on_depth_grid(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 analytic colour at the depth pixels' rays, and (H, W) face index."""
    face = trace(pose, K_DEPTH, W, H)[1]
    return FACE_COLOURS[face], face


def write_matrix(path: Path, M: np.ndarray) -> None:
    """A 4x4 matrix as four lines of four numbers (SensReader's text format)."""
    path.write_text("\n".join(" ".join(f"{x:.17g}" for x in row) for row in M) + "\n")


def write_scannet(root: Path, colour_ext: str = ".png") -> np.ndarray:
    """Write the ScanNet export of the room to ``root``; returns the true poses (n, 4, 4).

    ``colour_ext``: ``.png`` (lossless: the wall colours exact) or ``.jpg`` (SensReader's; a
    quality-100 JPEG, whose colours are off by a few levels near the walls' edges).
    """
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for name, K in (("intrinsic_depth.txt", K_DEPTH), ("intrinsic_color.txt", K_COLOUR)):
        K4 = np.eye(4)
        K4[:3, :3] = K
        write_matrix(root / "intrinsic" / name, K4)
    write_matrix(root / "intrinsic" / "extrinsic_color.txt", np.eye(4))
    write_matrix(root / "intrinsic" / "extrinsic_depth.txt", np.eye(4))
    poses = truth_poses()
    for k, pose in enumerate(poses):
        face = trace(pose, K_COLOUR, CW, CH)[1]
        kwargs = {"quality": 100} if colour_ext == ".jpg" else {}
        iio.imwrite(root / "color" / f"{k}{colour_ext}", FACE_COLOURS[face], **kwargs)
        iio.imwrite(root / "depth" / f"{k}.png", depth_mm(pose))
        write_matrix(root / "pose" / f"{k}.txt", np.full((4, 4), -np.inf) if k == BAD_FRAME else pose)
    return poses
