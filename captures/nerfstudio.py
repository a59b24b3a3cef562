"""Reader of nerfstudio's ``transforms.json`` capture layout (Record3D, Polycam, ARKit, COLMAP).

Layout (what ``ns-process-data`` writes)::

    transforms.json           intrinsics (top level or per frame), frames, poses
    images/frame_00001.png    colour
    depth/frame_00001.png     optional: uint16 depth in ``depth_unit_scale_factor`` metres
                              (default 1e-3: millimetres), or a float ``.npy`` in metres
    masks/frame_00001.png     optional mask (recorded, not used yet)

``transform_matrix`` is camera-to-world in metres with OpenGL camera axes (x right, y up,
looking down -z); it is turned to the project's OpenCV axes (x right, y down, z forward) by
flipping the camera's y and z. Intrinsics ``fl_x, fl_y, cx, cy, w, h`` are read from the frame,
else from the top level; nerfstudio's pixel centres are at ``u + 0.5``, as the project's.
``camera_model`` PINHOLE is read as is; OPENCV and OPENCV_FISHEYE only when every distortion
coefficient is 0 (distortion is refused, never ignored).

World: the poses stay in the world ``transform_matrix`` is written in (the one nerfstudio shows
and exports in, Z up for COLMAP data); ``applied_transform``, the rigid map ``ns-process-data``
applied to the original poses, is not undone but kept in ``Capture.meta["applied_transform"]``
(4x4), so a result can be taken back to the original reconstruction's world. The capture gives
no scene box: ``worldtogt`` is built from its cameras and depth (:mod:`regnf.captures.metric`).

Checked before any depth is read: the JSON, the camera model, distortion, every pose rigid,
every ``K`` valid, every file inside the folder and present, every image of size ``w x h``.
Then each depth file is read once for the bounds: an 8-bit depth PNG and a median depth beyond
:data:`MAX_MEDIAN_DEPTH_M` (a wrong ``depth_unit_scale_factor``) are refused there.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np

from regnf.captures.depth_io import PNG_SUFFIXES, read_depth
from regnf.captures.metric import SCENE_MARGIN, depth_points, metric_bounds
from regnf.captures.model import (
    Capture,
    CaptureError,
    CaptureFrame,
    apply_rule,
    capture_file,
    check_intrinsics,
    check_rigid_pose,
    far_plane,
    normalisation,
    pad_pose,
    parse_matrix,
    read_metadata,
)

TRANSFORMS_NAME = "transforms.json"
"""File name of a nerfstudio capture's metadata."""

CAMERA_MODELS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")
"""Camera models read (the distorted ones only with zero distortion)."""

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""Distortion coefficients of OPENCV / OPENCV_FISHEYE; a missing one is 0."""

DEFAULT_DEPTH_UNIT = 1e-3
"""Metres per unit of a depth PNG when ``depth_unit_scale_factor`` is absent (millimetres)."""

MAX_MEDIAN_DEPTH_M = 50.0
"""Largest median valid depth of a frame, in metres, accepted as a sensor's (a unit check)."""

NEAR = 0.05
"""Near plane of the scene box, in normalised units (as the sdfstudio writer's default)."""

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right factor turning an OpenGL-axes camera-to-world into an OpenCV-axes one."""


def detect(folder: Path) -> bool:
    """Whether ``folder`` holds a ``transforms.json``."""
    return (folder / TRANSFORMS_NAME).is_file()


def _number(value: Any, where: str) -> float:
    """A finite JSON number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CaptureError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _camera(data: dict, frame: dict, model: str, meta_path: Path, i: int) -> tuple[np.ndarray, int, int]:
    """``K`` (3, 3), width and height of frame ``i`` (its own keys first, then the top level)."""
    where = f"{meta_path}: frames[{i}]"
    got = {}
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        value = frame.get(key, data.get(key))
        if value is None:
            raise CaptureError(f"{where} has no {key!r} (neither in the frame nor at the top level)")
        got[key] = _number(value, f"{where}.{key}")
    w, h = got["w"], got["h"]
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise CaptureError(f"{where}: w and h must be positive integers, got {w:g} x {h:g}")
    distortion = {k: _number(frame.get(k, data.get(k, 0.0)), f"{where}.{k}") for k in DISTORTION_KEYS}
    nonzero = {k: v for k, v in distortion.items() if v != 0.0}
    if nonzero:
        coeffs = ", ".join(f"{k}={v:g}" for k, v in nonzero.items())
        # Name the top level when no coefficient is the frame's own: every frame has them.
        owner = where if any(k in frame for k in nonzero) else str(meta_path)
        raise CaptureError(
            f"{owner} has {coeffs} (camera_model {model}): distortion is not supported yet; "
            "undistort the images and set the coefficients to 0"
        )
    K = np.array([[got["fl_x"], 0.0, got["cx"]], [0.0, got["fl_y"], got["cy"]], [0.0, 0.0, 1.0]])
    apply_rule(check_intrinsics, K, where)
    return K, int(w), int(h)


def _check_image_size(path: Path, width: int, height: int, where: str) -> None:
    """Refuse a colour image whose header says another size than ``w x h``."""
    try:
        shape = iio.improps(path, extension=path.suffix or None).shape
    except Exception as exc:  # imageio raises many types for unreadable files
        raise CaptureError(f"{path}: {where}: cannot read image ({exc})") from exc
    if tuple(shape[:2]) != (height, width):
        raise CaptureError(
            f"{path}: {where}: image is {shape[1]}x{shape[0]} pixels, the metadata says "
            f"w x h = {width}x{height}"
        )


def read(path: str | Path) -> Capture:
    """Read and check a nerfstudio capture folder (or its ``transforms.json``).

    Raises
    ------
    CaptureError
        One line naming the file (and ``frames[i]``): bad JSON, an unknown camera model,
        non-zero distortion, a missing key, a non-rigid pose, a bad ``K``, a file missing or
        outside the folder, an image of another size than ``w x h``, a depth file that
        :func:`regnf.captures.depth_io.read_depth` refuses (an 8-bit PNG...), a median depth
        beyond :data:`MAX_MEDIAN_DEPTH_M`, or no depth at all.
    """
    path = Path(path)
    meta_path = path if path.suffix == ".json" and not path.is_dir() else path / TRANSFORMS_NAME
    meta_path = Path(os.path.abspath(meta_path))
    root = meta_path.parent
    data = read_metadata(meta_path)
    model = data.get("camera_model", "OPENCV")
    if model not in CAMERA_MODELS:
        raise CaptureError(
            f"{meta_path}: unknown camera_model {model!r}; supported: {', '.join(CAMERA_MODELS)}"
        )
    unit = _number(data.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT),
                   f"{meta_path}: depth_unit_scale_factor")
    if unit <= 0:
        raise CaptureError(f"{meta_path}: depth_unit_scale_factor must be > 0, got {unit:g}")
    raw = data.get("frames")
    if not isinstance(raw, list) or not raw:
        raise CaptureError(f"{meta_path}: 'frames' must be a non-empty list")
    meta: dict = {"format": "nerfstudio"}
    if data.get("applied_transform") is not None:
        applied = pad_pose(parse_matrix(data["applied_transform"], [(3, 4), (4, 4)],
                                        f"{meta_path}: applied_transform"))
        meta["applied_transform"] = applied.tolist()

    frames, poses, Ks, sizes = [], [], [], set()
    for i, f in enumerate(raw):
        where = f"{meta_path}: frames[{i}]"
        if not isinstance(f, dict):
            raise CaptureError(f"{where} must be an object")
        for key in ("file_path", "transform_matrix"):
            if key not in f:
                raise CaptureError(f"{where} is missing key {key!r}")
        K, w, h = _camera(data, f, model, meta_path, i)
        sizes.add((w, h))
        if len(sizes) > 1:
            raise CaptureError(f"{where}: frames of different sizes {sorted(sizes)} are not supported")
        gl = pad_pose(parse_matrix(f["transform_matrix"], [(4, 4), (3, 4)], f"{where}.transform_matrix"))
        apply_rule(check_rigid_pose, gl, f"{where}.transform_matrix")
        rgb = capture_file(root, f["file_path"], f"{where}.file_path")
        depth = f.get("depth_file_path")
        mask = f.get("mask_path")
        frames.append(CaptureFrame(
            rgb_path=rgb,
            depth_path=None if depth is None else capture_file(root, depth, f"{where}.depth_file_path"),
            camtoworld=gl @ OPENGL_TO_OPENCV,
            intrinsics=K,
            mask_path=None if mask is None else capture_file(root, mask, f"{where}.mask_path"),
        ))
        poses.append(gl @ OPENGL_TO_OPENCV)
        Ks.append(K)
    (width, height), = sizes
    for i, fr in enumerate(frames):
        _check_image_size(fr.rgb_path, width, height, f"frame {i}")
    if all(fr.depth_path is None for fr in frames):
        raise CaptureError(
            f"{meta_path}: no frame has a depth_file_path; regnf needs sensor depth "
            "(an RGB-only capture has no metric scene to bound)"
        )

    points = []
    for i, fr in enumerate(frames):
        if fr.depth_path is None:
            continue
        to_metres = unit if fr.depth_path.suffix.lower() in PNG_SUFFIXES else 1.0
        try:
            depth = read_depth(fr.depth_path, height, width, to_metres)
        except ValueError as exc:
            raise CaptureError(f"{fr.depth_path}: frame {i}: {exc}") from exc
        valid = depth[depth > 0]
        median = float(np.median(valid)) if valid.size else 0.0
        if median > MAX_MEDIAN_DEPTH_M:
            raise CaptureError(
                f"{fr.depth_path}: frame {i}: median depth {median:.4g} m is beyond "
                f"{MAX_MEDIAN_DEPTH_M:g} m with depth_unit_scale_factor {unit:g}: is the "
                "depth_unit_scale_factor right?"
            )
        points.append(depth_points(depth, Ks[i], poses[i]))
        fr.depth_scale = to_metres  # metres per file unit, normalised below

    pose_arr = np.stack(poses)
    worldtogt = normalisation(metric_bounds(pose_arr[:, :3, 3], np.concatenate(points)), SCENE_MARGIN)
    s, c = float(worldtogt[0, 0]), worldtogt[:3, 3]
    for fr in frames:
        fr.camtoworld = fr.camtoworld.copy()
        fr.camtoworld[:3, 3] = (fr.camtoworld[:3, 3] - c) / s
        fr.depth_scale = fr.depth_scale / s
    scene_box = {
        "aabb": np.array([[-1.0] * 3, [1.0] * 3]),
        "near": NEAR,
        "far": far_plane((pose_arr[:, :3, 3] - c) / s),
    }
    # nerfstudio documents no up axis for its world; its poses come from SLAM or COLMAP.
    return Capture(root, width, height, frames, worldtogt, scene_box, [], meta, TRANSFORMS_NAME,
                   up=None, poses_estimated=True)
