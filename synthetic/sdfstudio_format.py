"""Writer and loader of the sdfstudio-data ``meta_data.json`` capture layout.

Layout (one folder per capture)::

    meta_data.json            written LAST: a half-written capture has none
    000000_rgb.png            colour, uint8
    000000_depth.npy          float32 z-depth in NORMALISED units, 0 = no hit
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

The pose rules live here, at the bottom of the package graph (``synthetic`` ->
``neural_fields`` -> ... -> ``compositor``), so that training and rendering share them: the
renderer's :class:`~regnf.neural_fields.camera.Camera` and
:func:`regnf.neural_fields.similarity.decompose_similarity` call the same functions.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import trimesh

from regnf.core.atomic_io import atomic_path, write_json
from regnf.core.preflight import JsonInputError, input_file_problem, read_json_input
from regnf.synthetic.instance import Instance

META_NAME = "meta_data.json"
"""File name of the capture's metadata."""
MAX_META_BYTES = 256 * 2**20
"""Largest capture metadata file read, in bytes (about 400,000 frames)."""

SPLITS = ("train", "test", "val")
"""Accepted frame splits; frames without one are training frames."""


POSE_RTOL = 1e-5
"""Tolerance of the pose rules, on ``|A^T A / s^2 - I|``, on the last row and on ``|s - 1|``.

Poses stored in float32 are off by about 1e-7; a real scale, shear or skewed rotation is off
by far more than 1e-5, so this refuses every non-rigid pose and no rounding error."""


class CaptureError(ValueError):
    """A capture folder is missing, incomplete or malformed; the message names the file.

    The message is one line: a library's multi-line explanation (imageio's) is joined.
    """

    def __init__(self, message: str) -> None:
        super().__init__(re.sub(r"\s*[\r\n]+\s*", " ", str(message)))


# ----------------------------------------------------------------------------- pose rules


def similarity_scale(M: np.ndarray, rtol: float = POSE_RTOL) -> float:
    """The uniform scale ``s`` of a similarity ``M = [[s R, t], [0, 1]]`` (R a rotation).

    Parameters
    ----------
    M : (4, 4) float
        The matrix (array-like).
    rtol : float
        Tolerance on the last row and on ``|A^T A / s^2 - I|``.

    Returns
    -------
    float
        ``s = det(A) ** (1 / 3) > 0``, ``A = M[:3, :3]``.

    Raises
    ------
    ValueError
        Not 4x4 and finite, a last row other than ``[0, 0, 0, 1]``, a linear part with
        determinant <= 0 (singular, a reflection, a negative scale), or a non-uniform scale
        or shear. The message says which, without naming a file: callers add where.
    """
    try:
        M = np.asarray(M, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"a similarity must be a real 4x4 matrix ({exc})") from exc
    if M.shape != (4, 4):
        raise ValueError(f"a similarity must be 4x4, got shape {tuple(M.shape)}")
    if not np.isfinite(M).all():
        raise ValueError("similarity matrix has non-finite entries")
    if float(np.abs(M[3] - [0.0, 0.0, 0.0, 1.0]).max()) > rtol:
        raise ValueError(f"the last row of a similarity must be [0, 0, 0, 1], got {M[3].tolist()}")
    A = M[:3, :3]
    det = float(np.linalg.det(A))
    if not 0 < det < math.inf:
        raise ValueError(
            f"linear part has determinant {det:.6g}, not finite and > 0: a reflection, a negative "
            "scale or a degenerate matrix is not a similarity"
        )
    s = det ** (1.0 / 3.0)
    err = float(np.abs(A.T @ A / (s * s) - np.eye(3)).max())
    if not err <= rtol:  # also refuses NaN (entries so large that A^T A overflows)
        raise ValueError(
            f"not a uniformly scaled rotation (|A^T A / s^2 - I| = {err:.3g} > {rtol:g}): "
            "non-uniform scale or shear"
        )
    return s


def check_rigid_pose(M: np.ndarray, rtol: float = POSE_RTOL) -> None:
    """Refuse a camera-to-world ``M`` (4, 4) that is not a rotation plus a translation.

    The one rule for camera poses: training (:func:`load_capture`) and rendering
    (:class:`regnf.neural_fields.camera.Camera`) both call it, so a pose one accepts the other does.

    Raises
    ------
    ValueError
        See :func:`similarity_scale`; or a scale other than 1 (a rotation block scaled by
        7 is a similarity, not a pose).
    """
    s = similarity_scale(M, rtol)
    if abs(s - 1.0) > rtol:
        raise ValueError(f"must be rigid (scale 1), got scale {s:.6g}")


def check_intrinsics(K: np.ndarray) -> None:
    """Refuse a (3, 3) ``K`` that is not a pinhole matrix with positive focal lengths.

    ``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`` with finite entries and ``fx, fy > 0``
    (which also makes it invertible). Shared by :func:`load_capture` and
    :class:`regnf.neural_fields.camera.Camera`.

    Raises
    ------
    ValueError
        Wrong shape, non-finite entries, ``fx`` or ``fy`` <= 0, or a lower triangle other
        than ``[0, 0, 1]``.
    """
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"K must be a real 3x3 matrix ({exc})") from exc
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got shape {tuple(K.shape)}")
    if not np.isfinite(K).all():
        raise ValueError("K has non-finite values")
    fx, fy = float(K[0, 0]), float(K[1, 1])
    if not (fx > 0 and fy > 0):
        raise ValueError(f"focal lengths must be > 0, got fx = {fx:g}, fy = {fy:g}")
    lower = [float(K[1, 0]), float(K[2, 0]), float(K[2, 1]), float(K[2, 2])]
    if lower != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"not a pinhole K: K[1, 0], K[2, :] must be 0, [0, 0, 1], got {lower}")


@dataclass
class CaptureFrame:
    """One posed frame of a capture."""

    rgb_path: Path
    """Absolute path of the colour image."""
    depth_path: Path | None
    """Absolute path of the sensor depth (.npy, normalised units), None if absent."""
    camtoworld: np.ndarray
    """(4, 4) float64 OpenCV cam-to-world in the normalised frame."""
    intrinsics: np.ndarray
    """(3, 3) float64 pinhole K; pixel centres at (u + 0.5, v + 0.5)."""
    split: str = "train"
    """``train``, ``test`` or ``val``."""
    mono_depth_path: Path | None = None
    """Absolute path of a monocular depth prior, if the capture has one (unused by regnf)."""


@dataclass
class Capture:
    """A loaded capture: posed RGB-D frames in a normalised frame plus ground truth."""

    root: Path
    """Folder holding ``meta_data.json``."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    frames: list[CaptureFrame]
    """Frames in file order."""
    worldtogt: np.ndarray
    """(4, 4) float64 similarity, normalised frame -> metres."""
    scene_box: dict
    """``aabb`` (2, 3) float64 in the normalised frame, ``near``, ``far`` (and any extra keys)."""
    instances: list[Instance] = field(default_factory=list)
    """Placed objects (metres); empty for library captures or plain sdfstudio data."""
    meta: dict = field(default_factory=dict)
    """The ``regnf`` block of ``meta_data.json`` or {}."""

    @property
    def scale(self) -> float:
        """Metres per normalised unit (uniform scale of ``worldtogt``)."""
        return float(np.cbrt(abs(np.linalg.det(self.worldtogt[:3, :3]))))

    def rgb(self, i: int) -> np.ndarray:
        """Colour of frame ``i`` as (H, W, 3) float32 in [0, 1].

        Raises
        ------
        CaptureError
            Unreadable file, a dtype other than uint8 / uint16, or a shape other than
            (H, W), (H, W, 3) or (H, W, 4); the message names the file and the frame.
        """
        path = self.frames[i].rgb_path
        where = f"{path}: frame {i}"
        try:
            # The extension hint stops imageio from probing every plugin on a corrupt file.
            img = iio.imread(path, extension=path.suffix or None)
        except Exception as exc:  # imageio raises many types for unreadable files
            raise CaptureError(f"{where}: cannot read image ({exc})") from exc
        if img.dtype not in (np.uint8, np.uint16):
            raise CaptureError(f"{where}: image has dtype {img.dtype}, expected uint8 or uint16")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.ndim != 3 or img.shape[:2] != (self.height, self.width) or img.shape[2] not in (3, 4):
            raise CaptureError(
                f"{where}: image shape {img.shape} does not match {self.height}x{self.width} RGB(A)"
            )
        scale = 65535.0 if img.dtype == np.uint16 else 255.0
        return (img[..., :3].astype(np.float32) / np.float32(scale)).astype(np.float32)

    def depth(self, i: int) -> np.ndarray | None:
        """Sensor z-depth of frame ``i``, (H, W) float32 in normalised units; None if absent.

        Raises
        ------
        CaptureError
            Unreadable or pickled file, a dtype that is not real floating point (complex,
            integer, bool), a shape other than (H, W), or values that are NaN, infinite or
            negative (0 means no hit); the message names the file and the frame.
        """
        path = self.frames[i].depth_path
        if path is None:
            return None
        where = f"{path}: frame {i}"
        try:
            # Memory-mapped: the dtype and shape are checked before anything is read, so a
            # forged header asking for terabytes costs nothing.
            stored = np.load(path, allow_pickle=False, mmap_mode="r")
        except Exception as exc:  # corrupt, truncated or non-npy file
            raise CaptureError(f"{where}: cannot read depth ({exc})") from exc
        if not isinstance(stored, np.ndarray):
            raise CaptureError(f"{where}: depth must be one .npy array, got {type(stored).__name__}")
        if stored.dtype.kind != "f":
            raise CaptureError(
                f"{where}: depth has dtype {stored.dtype}, expected real floating point "
                "(float16, float32 or float64)"
            )
        if np.squeeze(stored).shape != (self.height, self.width):
            raise CaptureError(
                f"{where}: depth shape {stored.shape} does not match {self.height}x{self.width}"
            )
        # Cast first: a float64 value beyond float32's range becomes inf and is refused below.
        with np.errstate(over="ignore"):
            depth = np.squeeze(np.asarray(stored, dtype=np.float32))
        del stored
        bad = int(np.count_nonzero(~np.isfinite(depth)))
        if bad:
            raise CaptureError(f"{where}: depth has {bad} non-finite values (NaN or inf)")
        negative = int(np.count_nonzero(depth < 0))
        if negative:
            raise CaptureError(
                f"{where}: depth has {negative} negative values (min {float(depth.min()):g}); "
                "z-depth must be >= 0, 0 meaning no hit"
            )
        return depth

    def camtoworld_metres(self, i: int) -> np.ndarray:
        """(4, 4) float64 OpenCV cam-to-world of frame ``i`` in metres (rotation orthonormal).

        ``worldtogt = [[s R_w, c], [0, 1]]`` moves the camera centre to ``s R_w t + c`` and
        turns its axes by ``R_w``; the scale does not apply to the axes (the pose stays rigid).
        """
        pose = self.frames[i].camtoworld
        A = self.worldtogt[:3, :3]
        out = np.eye(4)
        out[:3, :3] = (A / similarity_scale(self.worldtogt)) @ pose[:3, :3]
        out[:3, 3] = A @ pose[:3, 3] + self.worldtogt[:3, 3]
        return out

    def train_indices(self) -> list[int]:
        """Indices of training frames."""
        return [i for i, f in enumerate(self.frames) if f.split == "train"]

    def test_indices(self) -> list[int]:
        """Indices of held-out frames (split ``test`` or ``val``)."""
        return [i for i, f in enumerate(self.frames) if f.split != "train"]

    def gt_mesh(self) -> trimesh.Trimesh | None:
        """The ground-truth mesh in metres, or None if the capture has none."""
        rel = self.meta.get("gt_mesh_path")
        if not rel:
            return None
        # Checked inside the folder by load_capture; checked again in case meta was edited.
        path = capture_file(self.root, rel, f"{self.root / META_NAME}: regnf.gt_mesh_path", must_exist=False)
        if not path.is_file():
            return None
        return trimesh.load(path, force="mesh", process=False)


# ----------------------------------------------------------------------------- loading helpers


def _matrix(value: Any, shapes: Sequence[tuple[int, ...]], where: str) -> np.ndarray:
    """Parse a nested list into a float64 array of one of ``shapes``, all finite."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{where} is not a numeric matrix ({exc})") from exc
    if arr.shape not in shapes:
        want = " or ".join("x".join(map(str, s)) for s in shapes)
        raise CaptureError(f"{where} must be {want}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CaptureError(f"{where} has non-finite values")
    return arr


def capture_file(root: Path, rel: Any, where: str, must_exist: bool = True) -> Path:
    """The file ``rel`` named in a capture's metadata, checked to lie inside ``root``.

    Parameters
    ----------
    root : Path
        The capture folder (absolute).
    rel : Any
        The path as stored in ``meta_data.json``; relative to ``root`` (absolute paths are
        accepted only if they too resolve inside it).
    where : str
        ``"<meta_data.json>: frames[i].rgb_path"``, for the message.
    must_exist : bool
        Also require a regular file there.

    Returns
    -------
    Path
        ``root / rel``.

    Raises
    ------
    CaptureError
        Not a non-empty string, resolving (symlinks followed, ``..`` applied) outside
        ``root``, or, with ``must_exist``, not an existing file.
    """
    if not isinstance(rel, str) or not rel or "\x00" in rel:
        raise CaptureError(f"{where} must be a non-empty path string, got {rel!r}")
    path = root / rel
    # realpath on both sides: a symlinked capture folder is fine, a symlink (or "..", or an
    # absolute path) leading out of it is not: training must read only the capture.
    real, base = Path(os.path.realpath(path)), Path(os.path.realpath(root))
    if not real.is_relative_to(base) or real == base:
        raise CaptureError(f"{where}: {rel!r} resolves to {real}, outside the capture folder {base}")
    if must_exist and not real.is_file():
        raise CaptureError(f"{where}: file {path} not found")
    return path


def _obey(rule: Callable[[np.ndarray], object], value: np.ndarray, where: str) -> None:
    """Apply a pose rule (a function raising ValueError) and name ``where`` if it fails."""
    try:
        rule(value)
    except ValueError as exc:
        raise CaptureError(f"{where}: {exc}") from exc


def _to_4x4(mat: np.ndarray) -> np.ndarray:
    """Pad a 3x4 pose with [0, 0, 0, 1]."""
    if mat.shape == (4, 4):
        return mat
    return np.vstack([mat, [0.0, 0.0, 0.0, 1.0]])


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
    camtoworld = _to_4x4(_matrix(data["camtoworld"], [(4, 4), (3, 4)], f"{where}.camtoworld"))
    _obey(check_rigid_pose, camtoworld, f"{where}.camtoworld")
    intrinsics = _matrix(data["intrinsics"], [(4, 4), (3, 3)], f"{where}.intrinsics")[:3, :3].copy()
    _obey(check_intrinsics, intrinsics, f"{where}.intrinsics")
    return CaptureFrame(
        rgb_path=capture_file(root, data["rgb_path"], f"{where}.rgb_path"),
        depth_path=None
        if depth_rel is None
        else capture_file(root, depth_rel, f"{where}.sensor_depth_path"),
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
    pose = _matrix(data["object_to_world"], [(4, 4)], f"{where}.object_to_world")
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
        box_corners=None if corners is None else _matrix(corners, [(8, 3)], f"{where}.box_corners"),
        mesh_path=None if not mesh_rel else capture_file(root, mesh_rel, f"{where}.mesh_path"),
    )


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
    problem = input_file_problem(meta_path, "file not found (is this a capture folder?)")
    if problem is not None:
        raise CaptureError(f"{meta_path}: {problem}")
    try:
        data = read_json_input(meta_path, None, "capture metadata", MAX_META_BYTES)
    except JsonInputError as exc:
        bad_text = isinstance(exc.__cause__, (UnicodeDecodeError, json.JSONDecodeError))
        raise CaptureError(f"{meta_path}: " + (f"invalid JSON ({exc.__cause__})" if bad_text else exc.problem)) from exc
    if not isinstance(data, dict):
        raise CaptureError(f"{meta_path}: top level must be a JSON object")
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
        worldtogt = _matrix(data["worldtogt"], [(4, 4)], f"{meta_path}: worldtogt")
        _obey(similarity_scale, worldtogt, f"{meta_path}: worldtogt")
    box = data.get("scene_box") or {}
    if not isinstance(box, dict):
        raise CaptureError(f"{meta_path}: scene_box must be an object")
    scene_box = dict(box)
    scene_box["aabb"] = _matrix(
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
    return Capture(root, width, height, frames, worldtogt, scene_box, instances, meta)


# ----------------------------------------------------------------------------- writing


def normalisation(bounds: np.ndarray, margin: float) -> np.ndarray:
    """``worldtogt`` for geometry with AABB ``bounds``: metres = s * normalised + c.

    Parameters
    ----------
    bounds : (2, 3) float
        Min and max corner in metres.
    margin : float
        Multiplier on half the largest extent (1.15 for library objects, 1.02 for rooms).

    Returns
    -------
    (4, 4) float64
    """
    bounds = np.asarray(bounds, dtype=np.float64)
    s = 0.5 * float(np.max(bounds[1] - bounds[0])) * margin
    out = np.eye(4)
    out[:3, :3] *= s
    out[:3, 3] = 0.5 * (bounds[0] + bounds[1])
    return out


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
        raise ValueError(f"write_capture({out}): need {n} 4x4 poses, got {poses.shape}")
    Ks = np.asarray(K, dtype=np.float64)
    Ks = np.broadcast_to(Ks, (n, 3, 3)) if Ks.shape == (3, 3) else Ks
    if Ks.shape != (n, 3, 3):
        raise ValueError(f"write_capture({out}): K must be 3x3 or ({n}, 3, 3), got {Ks.shape}")
    if frames_depth_metres is not None and len(frames_depth_metres) != n:
        raise ValueError(f"write_capture({out}): {len(frames_depth_metres)} depths for {n} frames")
    splits = ["train"] * n if splits is None else list(splits)
    if len(splits) != n or any(s not in SPLITS for s in splits):
        raise ValueError(f"write_capture({out}): need {n} splits from {SPLITS}")
    # The loader's rules, applied before any file is written: a capture this writes loads.
    for i in range(n):
        for rule, value, what in ((check_rigid_pose, poses[i], "pose"), (check_intrinsics, Ks[i], "K")):
            try:
                rule(value)
            except ValueError as exc:
                raise ValueError(f"write_capture({out}): frame {i} {what}: {exc}") from exc
    try:
        scale = similarity_scale(worldtogt)
    except ValueError as exc:
        raise ValueError(f"write_capture({out}): worldtogt: {exc}") from exc
    # Poses are normalised by moving their centres only (below), which is right only when
    # worldtogt does not rotate.
    turn = float(np.abs(np.asarray(worldtogt, np.float64)[:3, :3] / scale - np.eye(3)).max())
    if turn > POSE_RTOL:
        raise ValueError(f"write_capture({out}): worldtogt must not rotate (|A / s - I| = {turn:.3g})")
    for inst in instances:
        if inst.mesh_path is not None and not Path(inst.mesh_path).resolve().is_relative_to(out.resolve()):
            raise ValueError(
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
            raise ValueError(
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
    centres = (poses[:, :3, 3] - c) / s
    far = float(np.max(np.linalg.norm(centres, axis=1)) + np.sqrt(3.0))
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
