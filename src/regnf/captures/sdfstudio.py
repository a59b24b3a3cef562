"""Writer and loader of the sdfstudio-data ``meta_data.json`` capture layout.

Layout (one folder per capture)::

    meta_data.json            written LAST: a half-written capture has none
    000000_rgb.png            colour, uint8
    000000_depth.npy          float32 z-depth in NORMALISED units, 0 = no depth
    gt_mesh.ply, meshes/...   optional ground truth (metres)

``camtoworld`` is OpenCV (x right, y down, z forward) in the normalised frame; ``worldtogt``
maps normalised -> metres: ``metres = s * normalised + c``. The loader also accepts the plain
sdfstudio variants (no depth, ``mono_depth_path``, 3x3 or 4x4 intrinsics, no ``worldtogt``,
no ``instances``) so that real sdfstudio / ONR downloads load.

Nothing in ``meta_data.json`` is trusted. :func:`load_capture` checks, before any image is
read: every path it names resolves (symlinks followed) inside the capture folder, every
``camtoworld`` is a rigid pose (:func:`check_rigid_pose`), every ``K`` a pinhole matrix with
positive focal lengths (:func:`check_intrinsics`), ``worldtogt`` a similarity with a positive
uniform scale (:func:`similarity_scale`). :meth:`Capture.rgb` and :meth:`Capture.depth` check
each image's dtype, shape and values when it is read. Every failure is a :class:`CaptureError`
whose one-line message names the file and the frame.

The capture it loads is :class:`regnf.captures.model.Capture`, whose rules (poses, intrinsics,
paths) live in :mod:`regnf.captures.model`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np

from regnf.captures.depth_io import PNG_SUFFIXES, read_depth
from regnf.captures.depth_uncertainty import DEPTH_NOISE_KEY, parse_depth_noise
from regnf.captures.instance import Instance
from regnf.captures.metric import (
    check_median_depth,
    depth_points,
    metric_bounds,
    normalise_metric_frames,
)
from regnf.captures.model import (
    META_NAME,
    POSE_RTOL,
    REGNF_GENERATOR_PREFIX,
    SPLITS,
    Capture,
    CaptureError,
    CaptureFrame,
    apply_rule,
    capture_file,
    check_intrinsics,
    check_rigid_pose,
    far_plane,
    pad_pose,
    parse_matrix,
    read_metadata,
    similarity_scale,
    zero_depth_meaning,
)
from regnf.core.atomic_io import atomic_path, write_json
from regnf.core.errors import RegnfError


def detect(folder: Path) -> bool:
    """Whether ``folder`` holds a ``meta_data.json``."""
    return (folder / META_NAME).is_file()


def _load_frame(root: Path, data: Any, where: str) -> CaptureFrame:
    if not isinstance(data, dict):
        raise CaptureError(f"{where} must be an object")
    for key in ("rgb_path", "camtoworld", "intrinsics"):
        if key not in data:
            raise CaptureError(f"{where} is missing key {key!r}")
    split = data.get("split", "train")
    if split not in SPLITS:
        raise CaptureError(f"{where}.split must be one of {SPLITS}, got {split!r}")
    depth_rel = data.get("sensor_depth_path")
    mono_rel = data.get("mono_depth_path")
    camtoworld = pad_pose(parse_matrix(data["camtoworld"], [(4, 4), (3, 4)], f"{where}.camtoworld"))
    apply_rule(check_rigid_pose, camtoworld, f"{where}.camtoworld")
    intrinsics = parse_matrix(data["intrinsics"], [(4, 4), (3, 3)], f"{where}.intrinsics")[:3, :3].copy()
    apply_rule(check_intrinsics, intrinsics, f"{where}.intrinsics")
    rgb = capture_file(root, data["rgb_path"], f"{where}.rgb_path")
    depth = None if depth_rel is None else capture_file(root, depth_rel, f"{where}.sensor_depth_path")
    if depth is not None and depth.suffix.lower() in PNG_SUFFIXES:
        # meta_data.json states no depth unit: integer counts would be taken as normalised units.
        raise CaptureError(
            f"{where}.sensor_depth_path: {depth_rel!r} is a PNG, but meta_data.json states no depth "
            "unit; store z-depth as float .npy in normalised units"
        )
    return CaptureFrame(
        rgb_path=rgb,
        depth_path=depth,
        camtoworld=camtoworld,
        intrinsics=intrinsics,
        split=split,
        mono_depth_path=None
        if mono_rel is None
        else capture_file(root, mono_rel, f"{where}.mono_depth_path"),
    )


def _load_instance(root: Path, data: Any, where: str) -> Instance:
    if not isinstance(data, dict):
        raise CaptureError(f"{where} must be an object")
    for key in ("id", "object_to_world"):
        if key not in data:
            raise CaptureError(f"{where} is missing key {key!r}")
    pose = parse_matrix(data["object_to_world"], [(4, 4)], f"{where}.object_to_world")
    # Derive scale and yaw from the pose when a dataset does not state them.
    scale = data.get("scale")
    scale = float(np.cbrt(abs(np.linalg.det(pose[:3, :3])))) if scale is None else float(scale)
    yaw = data.get("yaw")
    yaw = float(np.arctan2(pose[1, 0], pose[0, 0])) if yaw is None else float(yaw)
    if not (np.isfinite(scale) and np.isfinite(yaw)):
        raise CaptureError(f"{where}: scale and yaw must be finite")
    corners = data.get("box_corners")
    mesh_rel = data.get("mesh_path")
    return Instance(
        id=str(data["id"]),
        library=str(data.get("library", data["id"])),
        label=str(data.get("class", data.get("label", "object"))),
        object_to_world=pose,
        scale=scale,
        yaw=yaw,
        box_corners=None if corners is None else parse_matrix(corners, [(8, 3)], f"{where}.box_corners"),
        mesh_path=None if not mesh_rel else capture_file(root, mesh_rel, f"{where}.mesh_path"),
    )


POSES_KEY = "poses"
"""Key of the ``regnf`` block that says whether the poses are ``exact`` or ``estimated``."""


def poses_are_estimates(meta: dict, ideal: bool) -> bool:
    """Whether an sdfstudio capture's poses are estimates (refined in training by default).

    :data:`POSES_KEY` says so where present; otherwise the poses of an ideal capture (one whose
    zero depth means empty: regnf's own noiseless renders, or a capture that says so) are exact
    and every other capture's are estimates, as a real scan's are.

    Raises
    ------
    ValueError
        :data:`POSES_KEY` with a value other than ``exact`` or ``estimated``.
    """
    value = meta.get(POSES_KEY)
    if value is None:
        return not ideal
    if value not in ("exact", "estimated"):
        raise RegnfError(f"regnf.{POSES_KEY} must be 'exact' or 'estimated', got {value!r}")
    return value == "estimated"


def _unboxed_bounds(frames: list[CaptureFrame], width: int, height: int, meta_path: Path,
                    scene_box: dict, meta: dict) -> tuple[np.ndarray, dict]:
    """``worldtogt`` and scene box of a capture that states neither (poses and depth in metres).

    Such a capture is taken as it stands (the identity, the unit box) when its cameras and the
    robust bounds of its depth (:func:`regnf.captures.metric.metric_bounds`) fit in the unit box,
    as a capture already normalised does; otherwise it is in metres, and it is normalised from
    those bounds (:func:`regnf.captures.metric.normalise_metric_frames`) rather than cropped to
    a 2 m cube.
    """
    unknown = zero_depth_meaning(meta) == "unknown"
    points = []
    for i, fr in enumerate(frames):
        if fr.depth_path is None:
            continue
        try:
            depth = read_depth(fr.depth_path, height, width, fr.depth_scale, unknown)
        except ValueError as exc:
            raise CaptureError(f"{fr.depth_path}: frame {i}: {exc}") from exc
        check_median_depth(depth, f"{fr.depth_path}: frame {i}", "read as metres: is the depth in metres?")
        points.append(depth_points(depth, fr.intrinsics, fr.camtoworld))
    pts = np.concatenate(points) if points else np.zeros((0, 3))
    centres = np.stack([fr.camtoworld[:3, 3] for fr in frames])
    bounds = metric_bounds(centres, pts)
    if float(np.abs(bounds).max()) <= 1.0:
        return np.eye(4), scene_box
    return normalise_metric_frames(frames, pts)


def load_capture(path: str | Path) -> Capture:
    """Load and validate a capture folder (or its ``meta_data.json``).

    Everything the metadata says is checked here, before any image is read (see the module
    docstring); images and depths are checked as they are read.

    Raises
    ------
    CaptureError
        On a missing folder or file, bad JSON, missing keys, wrong matrix shapes or non-finite
        values, a path leading outside the folder, a non-rigid or singular pose, a ``K``
        with focal lengths <= 0, a ``worldtogt`` that is not a similarity; the message names
        the offending file and entry (``frames[i]``).
    """
    path = Path(path)
    meta_path = path / META_NAME if path.is_dir() or path.suffix != ".json" else path
    # Absolute (not resolved: the user's spelling stays readable in messages), so that frame
    # paths, provenance and cache keys do not depend on the working directory.
    meta_path = Path(os.path.abspath(meta_path))
    root = meta_path.parent
    data = read_metadata(meta_path)
    for key in ("height", "width", "frames"):
        if key not in data:
            raise CaptureError(f"{meta_path}: missing key {key!r}")
    model = data.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE"):
        raise CaptureError(f"{meta_path}: unsupported camera_model {model!r} (pinhole only)")
    try:
        width, height = int(data["width"]), int(data["height"])
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{meta_path}: width/height must be integers") from exc
    if width <= 0 or height <= 0:
        raise CaptureError(f"{meta_path}: width/height must be positive, got {width}x{height}")
    if not isinstance(data["frames"], list) or not data["frames"]:
        raise CaptureError(f"{meta_path}: 'frames' must be a non-empty list")
    frames = [
        _load_frame(root, f, f"{meta_path}: frames[{i}]") for i, f in enumerate(data["frames"])
    ]
    worldtogt = np.eye(4)
    if data.get("worldtogt") is not None:
        worldtogt = parse_matrix(data["worldtogt"], [(4, 4)], f"{meta_path}: worldtogt")
        apply_rule(similarity_scale, worldtogt, f"{meta_path}: worldtogt")
    box = data.get("scene_box") or {}
    if not isinstance(box, dict):
        raise CaptureError(f"{meta_path}: scene_box must be an object")
    scene_box = dict(box)
    scene_box["aabb"] = parse_matrix(
        box.get("aabb", [[-1.0] * 3, [1.0] * 3]), [(2, 3)], f"{meta_path}: scene_box.aabb"
    )
    for key, default in (("near", 0.05), ("far", 4.0)):
        value = box.get(key, default)
        if not isinstance(value, (int, float)) or not np.isfinite(value):
            raise CaptureError(f"{meta_path}: scene_box.{key} must be a finite number")
        scene_box[key] = float(value)
    raw_instances = data.get("instances") or []
    if not isinstance(raw_instances, list):
        raise CaptureError(f"{meta_path}: 'instances' must be a list")
    instances = [
        _load_instance(root, d, f"{meta_path}: instances[{i}]") for i, d in enumerate(raw_instances)
    ]
    meta = data.get("regnf") or {}
    if not isinstance(meta, dict):
        raise CaptureError(f"{meta_path}: 'regnf' must be an object")
    if meta.get("gt_mesh_path"):
        capture_file(root, meta["gt_mesh_path"], f"{meta_path}: regnf.gt_mesh_path", must_exist=False)
    try:
        zeros = zero_depth_meaning(meta)
        estimated = poses_are_estimates(meta, ideal=zeros == "empty")
        if DEPTH_NOISE_KEY in meta:
            parse_depth_noise(meta[DEPTH_NOISE_KEY])
    except ValueError as exc:
        raise CaptureError(f"{meta_path}: {exc}") from exc
    if data.get("worldtogt") is None and not data.get("scene_box"):
        worldtogt, scene_box = _unboxed_bounds(frames, width, height, meta_path, scene_box, meta)
    generator = meta.get("generator")
    ours = isinstance(generator, str) and generator.startswith(REGNF_GENERATOR_PREFIX)
    # regnf's renders are +Z up.
    up = np.array([0.0, 0.0, 1.0]) if ours else None
    return Capture(root, width, height, frames, worldtogt, scene_box, instances, meta,
                   up=up, poses_estimated=estimated)


# ----------------------------------------------------------------------------- writing


def write_capture(
    out_dir: str | Path,
    frames_rgb: Sequence[np.ndarray],
    frames_depth_metres: Sequence[np.ndarray] | None,
    camtoworld_metres: np.ndarray,
    K: np.ndarray,
    worldtogt: np.ndarray,
    instances: Sequence[Instance] = (),
    meta: dict | None = None,
    splits: Sequence[str] | None = None,
    near: float = 0.05,
) -> Path:
    """Write a capture folder; every file atomically, ``meta_data.json`` last.

    Parameters
    ----------
    frames_rgb : sequence of (H, W, 3) uint8
        Colour images.
    frames_depth_metres : sequence of (H, W) float, or None
        z-depth in metres (0 = no hit); stored divided by the scale of ``worldtogt``.
    camtoworld_metres : (n, 4, 4) float
        OpenCV cam-to-world poses in metres.
    K : (3, 3) or (n, 3, 3) float
        Intrinsics, shared or per frame.
    worldtogt : (4, 4) float
        Normalised -> metres similarity (uniform scale, no rotation).
    instances : sequence of Instance
        Placed objects (metres); their ``mesh_path`` must lie inside ``out_dir`` and is stored
        relative to it.
    meta : dict, optional
        The ``regnf`` block.
    splits : sequence of str, optional
        Per-frame split; all ``train`` if None.

    Returns
    -------
    Path
        The written ``meta_data.json``.

    Raises
    ------
    ValueError
        Before anything is written: inconsistent counts or shapes, a pose that is not rigid,
        a ``K`` that :func:`check_intrinsics` refuses, a ``worldtogt`` that is not a
        similarity, an instance mesh outside ``out_dir``.
    """
    out = Path(out_dir)
    poses = np.asarray(camtoworld_metres, dtype=np.float64)
    n = len(frames_rgb)
    if poses.shape != (n, 4, 4):
        raise RegnfError(f"write_capture({out}): need {n} 4x4 poses, got {poses.shape}")
    Ks = np.asarray(K, dtype=np.float64)
    Ks = np.broadcast_to(Ks, (n, 3, 3)) if Ks.shape == (3, 3) else Ks
    if Ks.shape != (n, 3, 3):
        raise RegnfError(f"write_capture({out}): K must be 3x3 or ({n}, 3, 3), got {Ks.shape}")
    if frames_depth_metres is not None and len(frames_depth_metres) != n:
        raise RegnfError(f"write_capture({out}): {len(frames_depth_metres)} depths for {n} frames")
    splits = ["train"] * n if splits is None else list(splits)
    if len(splits) != n or any(s not in SPLITS for s in splits):
        raise RegnfError(f"write_capture({out}): need {n} splits from {SPLITS}")
    # The loader's rules, applied before any file is written: a capture this writes loads.
    for i in range(n):
        for rule, value, what in ((check_rigid_pose, poses[i], "pose"), (check_intrinsics, Ks[i], "K")):
            try:
                rule(value)
            except ValueError as exc:
                raise RegnfError(f"write_capture({out}): frame {i} {what}: {exc}") from exc
    try:
        scale = similarity_scale(worldtogt)
    except ValueError as exc:
        raise RegnfError(f"write_capture({out}): worldtogt: {exc}") from exc
    # Poses are normalised by moving their centres only (below), which is right only when
    # worldtogt does not rotate.
    turn = float(np.abs(np.asarray(worldtogt, np.float64)[:3, :3] / scale - np.eye(3)).max())
    if turn > POSE_RTOL:
        raise RegnfError(f"write_capture({out}): worldtogt must not rotate (|A / s - I| = {turn:.3g})")
    for inst in instances:
        if inst.mesh_path is not None and not Path(inst.mesh_path).resolve().is_relative_to(out.resolve()):
            raise RegnfError(
                f"write_capture({out}): instance {inst.id!r} mesh {inst.mesh_path} is outside the "
                "capture folder (a capture may name only files inside it)"
            )
    height, width = np.asarray(frames_rgb[0]).shape[:2]
    s = float(np.cbrt(np.linalg.det(worldtogt[:3, :3])))
    c = np.asarray(worldtogt, dtype=np.float64)[:3, 3]
    out.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):  # one file per frame
        rgb = np.asarray(frames_rgb[i])
        if rgb.shape != (height, width, 3) or rgb.dtype != np.uint8:
            raise RegnfError(
                f"write_capture({out}): frame {i} rgb must be ({height}, {width}, 3) uint8"
            )
        rgb_name = f"{i:06d}_rgb.png"
        with atomic_path(out / rgb_name) as tmp:
            iio.imwrite(tmp, rgb)
        pose = poses[i].copy()
        pose[:3, 3] = (pose[:3, 3] - c) / s
        K4 = np.eye(4)
        K4[:3, :3] = Ks[i]
        frame = {"rgb_path": rgb_name, "camtoworld": pose.tolist(), "intrinsics": K4.tolist()}
        if frames_depth_metres is not None:
            depth = np.asarray(frames_depth_metres[i], dtype=np.float32) / np.float32(s)
            depth_name = f"{i:06d}_depth.npy"
            with atomic_path(out / depth_name) as tmp:
                np.save(tmp, depth.astype(np.float32), allow_pickle=False)
            frame["sensor_depth_path"] = depth_name
        frame["split"] = splits[i]
        frames.append(frame)
    far = far_plane((poses[:, :3, 3] - c) / s)
    inst_json = []
    for inst in instances:
        rel = None
        if inst.mesh_path is not None:
            rel = Path(inst.mesh_path).resolve().relative_to(out.resolve()).as_posix()
        inst_json.append(inst.to_json(mesh_path=rel))
    data = {
        "camera_model": "OPENCV",
        "height": int(height),
        "width": int(width),
        "has_mono_prior": False,
        "has_sensor_depth": frames_depth_metres is not None,
        "pairs": None,
        "worldtogt": np.asarray(worldtogt, dtype=np.float64).tolist(),
        "scene_box": {
            "aabb": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]],
            "near": float(near),
            "far": far,
            "radius": 1.0,
            "collider_type": "box",
        },
        "frames": frames,
        "instances": inst_json,
        "regnf": dict(meta or {}),
    }
    meta_path = out / META_NAME
    write_json(meta_path, data)
    return meta_path
