"""Reader of nerfstudio's ``transforms.json`` capture layout (Record3D, Polycam, ARKit, COLMAP).

Layout (what ``ns-process-data`` writes)::

    transforms.json           intrinsics (top level or per frame), frames, poses
    images/frame_00001.png    colour
    depth/frame_00001.png     optional: uint16 depth in ``depth_unit_scale_factor`` metres
                              (default 1e-3: millimetres), or a float ``.npy`` in metres
    masks/frame_00001.png     optional mask (recorded, not used yet)
    confidence/frame_00001.png optional ``confidence_path``: uint8 depth confidence, ARKit's
                              0 low (the depth is unknown), 1 medium, 2 high

``transform_matrix`` is camera-to-world in metres with OpenGL camera axes (x right, y up,
looking down -z); it is turned to the project's OpenCV axes (x right, y down, z forward) by
flipping the camera's y and z. Intrinsics ``fl_x, fl_y, cx, cy, w, h`` are read from the frame,
else from the top level; nerfstudio's pixel centres are at ``u + 0.5``, as the project's.
``camera_model`` PINHOLE is read as is (non-zero distortion coefficients refused); OPENCV
(``k1, k2, k3, p1, p2``; ``k4`` must be 0) and OPENCV_FISHEYE (equidistant ``k1..k4``; ``p1, p2``
must be 0) give each frame a :class:`~regnf.captures.distortion.Distortion`, global or per
frame, that every pixel -> ray and point -> pixel applies; a model that folds over inside the
image is refused (:func:`~regnf.captures.distortion.check_invertible`). Where every coefficient
is 0 the frame is a plain pinhole (``distortion`` None), exactly as a PINHOLE one.

World: the poses stay in the world ``transform_matrix`` is written in (the one nerfstudio shows
and exports in, Z up for COLMAP data); ``applied_transform``, the rigid map ``ns-process-data``
applied to the original poses, is not undone but kept in ``Capture.meta["applied_transform"]``
(4x4), so a result can be taken back to the original reconstruction's world. The capture gives
no scene box: ``worldtogt`` is built from its cameras and depth (:mod:`regnf.captures.metric`).

Checked before any depth is read: the JSON, the camera model, distortion (coefficients the
model has, and invertible over the image), every pose rigid,
every ``K`` valid, every file inside the folder and present, every image of size ``w x h``.
Then each depth file is read once for the bounds: an 8-bit depth PNG and a median depth beyond
:data:`~regnf.captures.metric.MAX_MEDIAN_DEPTH_M` (a wrong ``depth_unit_scale_factor``) are refused there.
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np

from regnf.captures.depth_io import PNG_SUFFIXES, read_depth
from regnf.captures.distortion import Distortion, check_invertible
from regnf.captures.metric import check_median_depth, depth_points, normalise_metric_frames
from regnf.captures.model import (
    Capture,
    CaptureError,
    CaptureFrame,
    apply_rule,
    capture_file,
    check_intrinsics,
    check_rigid_pose,
    pad_pose,
    parse_matrix,
    read_metadata,
)

TRANSFORMS_NAME = "transforms.json"
"""File name of a nerfstudio capture's metadata."""

CAMERA_MODELS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")
"""Camera models read."""

UNUSED_COEFFICIENTS = {"PINHOLE": ("k1", "k2", "k3", "k4", "p1", "p2"), "OPENCV": ("k4",),
                       "OPENCV_FISHEYE": ("p1", "p2")}
"""Per camera model, the coefficients it does not have: non-zero ones are refused, never ignored."""

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
"""Distortion coefficients of OPENCV / OPENCV_FISHEYE; a missing one is 0."""

DEFAULT_DEPTH_UNIT = 1e-3
"""Metres per unit of a depth PNG when ``depth_unit_scale_factor`` is absent (millimetres)."""

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


def _camera(data: dict, frame: dict, model: str, meta_path: Path,
            i: int) -> tuple[np.ndarray, int, int, Distortion | None]:
    """``K`` (3, 3), width, height and distortion of frame ``i`` (its own keys first, then the top level)."""
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
    coeffs = {k: _number(frame.get(k, data.get(k, 0.0)), f"{where}.{k}") for k in DISTORTION_KEYS}
    nonzero = {k: v for k, v in coeffs.items() if v != 0.0}
    K = np.array([[got["fl_x"], 0.0, got["cx"]], [0.0, got["fl_y"], got["cy"]], [0.0, 0.0, 1.0]])
    apply_rule(check_intrinsics, K, where)
    if not nonzero:
        return K, int(w), int(h), None
    listed = ", ".join(f"{k}={v:g}" for k, v in nonzero.items())
    # Name the top level when no coefficient is the frame's own: every frame has them.
    owner = where if any(k in frame for k in nonzero) else str(meta_path)
    unused = [k for k in nonzero if k in UNUSED_COEFFICIENTS[model]]
    if unused:
        raise CaptureError(
            f"{owner} has {listed} (camera_model {model}): {model} has no {', '.join(unused)}; "
            "set it to 0 or name the camera_model whose coefficients these are"
        )
    distortion = Distortion(model, **{k: coeffs[k] for k in DISTORTION_KEYS if k not in UNUSED_COEFFICIENTS[model]})
    try:
        _check_lens(distortion, tuple(K.ravel().tolist()), int(w), int(h))
    except ValueError as exc:
        raise CaptureError(f"{owner}: {exc}") from exc
    return K, int(w), int(h), distortion


@functools.lru_cache(maxsize=64)
def _check_lens(distortion: Distortion, K: tuple[float, ...], width: int, height: int) -> None:
    """:func:`check_invertible` once per camera (frames share their coefficients and ``K``)."""
    check_invertible(distortion, np.reshape(K, (3, 3)), width, height)


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
        a distortion coefficient the camera model has not, a lens model that folds over
        inside the image, a missing key, a non-rigid pose, a bad ``K``, a file missing or
        outside the folder, an image of another size than ``w x h``, a depth file that
        :func:`regnf.captures.depth_io.read_depth` refuses (an 8-bit PNG...), a median depth
        beyond :data:`~regnf.captures.metric.MAX_MEDIAN_DEPTH_M`, or no depth at all.
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
        K, w, h, distortion = _camera(data, f, model, meta_path, i)
        sizes.add((w, h))
        if len(sizes) > 1:
            raise CaptureError(f"{where}: frames of different sizes {sorted(sizes)} are not supported")
        gl = pad_pose(parse_matrix(f["transform_matrix"], [(4, 4), (3, 4)], f"{where}.transform_matrix"))
        apply_rule(check_rigid_pose, gl, f"{where}.transform_matrix")
        rgb = capture_file(root, f["file_path"], f"{where}.file_path")
        depth = f.get("depth_file_path")
        mask = f.get("mask_path")
        confidence = f.get("confidence_path")
        frames.append(CaptureFrame(
            rgb_path=rgb,
            depth_path=None if depth is None else capture_file(root, depth, f"{where}.depth_file_path"),
            camtoworld=gl @ OPENGL_TO_OPENCV,
            intrinsics=K,
            distortion=distortion,
            mask_path=None if mask is None else capture_file(root, mask, f"{where}.mask_path"),
            confidence_path=None if confidence is None else capture_file(root, confidence, f"{where}.confidence_path"),
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
        check_median_depth(depth, f"{fr.depth_path}: frame {i}",
                           f"with depth_unit_scale_factor {unit:g}: is the depth_unit_scale_factor right?")
        points.append(depth_points(depth, Ks[i], poses[i], fr.distortion))
        fr.depth_scale = to_metres  # metres per file unit, normalised below

    worldtogt, scene_box = normalise_metric_frames(frames, np.concatenate(points))
    # nerfstudio documents no up axis for its world; its poses come from SLAM or COLMAP.
    return Capture(root, width, height, frames, worldtogt, scene_box, [], meta, TRANSFORMS_NAME,
                   up=None, poses_estimated=True)
