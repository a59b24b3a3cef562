"""The pose error of the cameras that see an object, for the sensor benchmark.

A noisy room capture (:mod:`regnf.synthetic.sensor_noise`) stores the poses a SLAM system
would report while its images were rendered from the true ones, kept beside it in
:data:`~regnf.synthetic.sensor_noise.TRUE_POSES_NAME`. The map built from such a capture is off
by about the error of the cameras that observed each part of it, so an object's registration
is judged against the error of the cameras that see that object.

A training camera *sees* an instance when, of a :data:`GRID` ^ 3 grid of points spanning the
instance's true box, at least :data:`SEEN_FRACTION` project into the image, in front of the
camera (true pose), at pixels whose measured depth, back-projected along the pixel's ray, lands
inside the box (grown by :data:`BOX_PAD` of its size): at those pixels the camera measured the
object, not something in front of it or the floor and walls behind or beside it. A pixel without
a return (depth 0) does not count. The numbers: docs/decisions/sensor_benchmark.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regnf.captures.instance import Instance
from regnf.captures.model import Capture
from regnf.core.errors import RegnfError
from regnf.core.preflight import read_json_input
from regnf.fields.oriented_box import OrientedBox
from regnf.synthetic.pose_noise import pose_errors
from regnf.synthetic.sensor_noise import TRUE_POSES_NAME

BOX_PAD = 0.05
"""Growth of each half extent of an instance's box, as a fraction of it, for the depth test
(a measured surface point a few millimetres outside the true box still lies on the object)."""
GRID = 5
"""Points per box axis of the grid projected into each camera."""
SEEN_FRACTION = 0.1
"""Fraction of the grid's points at which a camera must measure the object to see it."""


def true_camtoworld(capture: Capture) -> np.ndarray:
    """(n, 4, 4) float64 true OpenCV camera-to-world poses of every frame, metres.

    An ideal capture (no ``noise`` block in its metadata) stores its true poses; a noisy one
    keeps them in :data:`~regnf.synthetic.sensor_noise.TRUE_POSES_NAME` beside its metadata.

    Raises
    ------
    ValueError
        A noisy capture whose true-pose file is missing, unreadable or holds another number
        of poses than the capture has frames (the message names the file).
    """
    stored = np.stack([capture.camtoworld_metres(i) for i in range(len(capture.frames))])
    if not capture.meta.get("noise"):
        return stored
    path = Path(capture.root) / TRUE_POSES_NAME
    data = read_json_input(path, None, "true-pose file")
    poses = np.asarray(data.get("camtoworld_metres") if isinstance(data, dict) else None, dtype=np.float64)
    if poses.shape != stored.shape:
        raise RegnfError(f"{path}: expected {stored.shape[0]} (4, 4) poses in camtoworld_metres, "
                         f"got shape {poses.shape}")
    return poses


def box_grid(box: OrientedBox, n: int = GRID) -> np.ndarray:
    """(n^3, 3) points of a regular grid spanning ``box``, inset half a step from its faces."""
    ticks = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    u = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)
    return box.center + (u * box.half_extents) @ box.rotation.T


def cameras_seeing(capture: Capture, true_c2w: np.ndarray, indices: list[int],
                   instances: list[Instance]) -> np.ndarray:
    """Which of frames ``indices`` see which instance (the rule of the module).

    Parameters
    ----------
    capture : Capture
        Its depth images are read (one frame at a time).
    true_c2w : (n_frames, 4, 4) float
        True camera-to-world poses of every frame of the capture, metres.
    indices : list of int
        The frames to test (k of them).
    instances : list of Instance
        Instances with box corners (m of them), room metres.

    Returns
    -------
    (k, m) bool
    """
    if not instances:
        return np.zeros((len(indices), 0), dtype=bool)
    boxes = [OrientedBox.from_corners(inst.box_corners) for inst in instances]
    grid = np.concatenate([box_grid(b) for b in boxes])  # (m g, 3), g = GRID^3 per box
    c2w = np.asarray(true_c2w, dtype=np.float64)[indices]
    R, t = c2w[:, :3, :3], c2w[:, :3, 3]
    cam = np.einsum("kji,kpj->kpi", R, grid[None] - t[:, None])  # R^T (x - t): (k, m g, 3)
    K = np.stack([np.asarray(capture.frames[i].intrinsics, dtype=np.float64) for i in indices])
    fx, fy, cx, cy = (K[:, None, 0, 0], K[:, None, 1, 1], K[:, None, 0, 2], K[:, None, 1, 2])
    z = cam[..., 2]
    safe_z = np.where(z > 0, z, 1.0)
    col = np.floor(fx * cam[..., 0] / safe_z + cx).astype(np.int64)
    row = np.floor(fy * cam[..., 1] / safe_z + cy).astype(np.int64)
    inside = (z > 0) & (col >= 0) & (col < capture.width) & (row >= 0) & (row < capture.height)
    col, row = np.clip(col, 0, capture.width - 1), np.clip(row, 0, capture.height - 1)
    measured = np.zeros(z.shape)
    for a, i in enumerate(indices):  # one depth image per frame
        depth = capture.depth(i)
        if depth is not None:
            measured[a] = depth[row[a], col[a]].astype(np.float64) * capture.scale
    # The measured point along the pixel's ray (camera z of 1 at the pixel centre).
    rays = np.stack([(col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy, np.ones(z.shape)], -1)
    points = np.einsum("kij,kpj->kpi", R, rays * measured[..., None]) + t[:, None]
    per_box = len(grid) // len(boxes)
    in_box = np.concatenate([b.contains(points[:, j * per_box:(j + 1) * per_box].reshape(-1, 3), BOX_PAD)
                             .reshape(len(indices), per_box) for j, b in enumerate(boxes)], axis=1)
    hit = inside & (measured > 0) & in_box
    return hit.reshape(len(indices), len(boxes), per_box).mean(-1) >= SEEN_FRACTION


def object_camera_errors(capture: Capture, instances: list[Instance] | None = None) -> dict[str, dict]:
    """Per instance, the median pose error of the training cameras that see it.

    Parameters
    ----------
    capture : Capture
        A room capture whose instances have boxes (ideal or noisy, see :func:`true_camtoworld`).
    instances : list of Instance, optional
        Default: every instance of the capture.

    Returns
    -------
    dict
        Instance id -> ``cameras`` (how many training cameras see it), ``position_cm`` and
        ``rotation_deg`` (the medians of their position and orientation errors; None when no
        camera sees it).
    """
    instances = list(capture.instances if instances is None else instances)
    indices = capture.train_indices()
    true = true_camtoworld(capture)
    stored = np.stack([capture.camtoworld_metres(i) for i in indices])
    position, rotation = pose_errors(stored, true[indices])
    seen = cameras_seeing(capture, true, indices, instances)
    out = {}
    for j, inst in enumerate(instances):
        k = seen[:, j]
        out[inst.id] = {"cameras": int(k.sum()),
                        "position_cm": float(100.0 * np.median(position[k])) if k.any() else None,
                        "rotation_deg": float(np.median(rotation[k])) if k.any() else None}
    return out
