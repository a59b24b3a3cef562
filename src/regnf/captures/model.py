"""The in-memory capture every format reader produces, and the rules its poses obey.

A :class:`Capture` is posed RGB-D frames in a NORMALISED frame plus ``worldtogt``, the
similarity normalised -> metres (``metres = s * normalised + c``), so that every result can be
written in the capture's own metric world. ``camtoworld`` is OpenCV (x right, y down, z forward);
``K`` is a pinhole matrix with pixel centres at ``(u + 0.5, v + 0.5)``. Depth is z-depth, read
per frame from ``.npy`` (float) or 16-bit PNG and scaled by the frame's ``depth_scale`` into
normalised units; 0 means no depth. What a pixel without depth says depends on the capture
(:attr:`Capture.zero_depth_is_empty`): for regnf's own ideal renders the ray hit nothing, for
every other capture (a real sensor, a noisy render) the depth is unknown.

The pose rules live here, at the bottom of the package graph (``core`` -> ``captures`` ->
``observations`` -> ``fields`` -> ...), so that every reader, training and rendering share
them: the renderer's :class:`~regnf.render.camera.Camera` and
:func:`regnf.fields.similarity.decompose_similarity` call the same functions.
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

from regnf.captures.depth_io import read_depth
from regnf.captures.depth_uncertainty import DEPTH_NOISE_KEY, DepthNoiseModel, parse_depth_noise
from regnf.captures.distortion import Distortion
from regnf.captures.instance import Instance
from regnf.captures.resample import resample_to_grid
from regnf.core.errors import RegnfError
from regnf.core.preflight import JsonInputError, input_file_problem, read_json_input

META_NAME = "meta_data.json"
"""File name of the sdfstudio capture metadata (the default :attr:`Capture.meta_name`)."""

MAX_META_BYTES = 256 * 2**20
"""Largest capture metadata file read, in bytes (about 400,000 frames)."""

REGNF_GENERATOR_PREFIX = "regnf.synthetic/"
"""Start of ``regnf.generator`` in the captures regnf's own renderer writes."""

ZERO_DEPTH_KEY = "zero_depth"
"""Key of the ``regnf`` block that overrides what a zero depth means: ``empty`` or ``unknown``."""

ZERO_DEPTH_MEANINGS = ("empty", "unknown")
"""Accepted values of :data:`ZERO_DEPTH_KEY`."""


def zero_depth_meaning(meta: dict) -> str:
    """What a pixel without depth means in a capture whose ``regnf`` block is ``meta``.

    ``"empty"`` (the ray hit nothing) only for regnf's own renders with ideal depth: the
    generator is regnf's and there is no ``noise`` block. Everything else is ``"unknown"``: a
    sensor writes 0 where it has no return, which says nothing about the space along the ray.
    :data:`ZERO_DEPTH_KEY` overrides the rule.

    Raises
    ------
    ValueError
        :data:`ZERO_DEPTH_KEY` present with a value other than ``empty`` or ``unknown``.
    """
    if ZERO_DEPTH_KEY in meta:
        value = meta[ZERO_DEPTH_KEY]
        if value not in ZERO_DEPTH_MEANINGS:
            raise RegnfError(f"regnf.{ZERO_DEPTH_KEY} must be 'empty' or 'unknown', got {value!r}")
        return str(value)
    generator = meta.get("generator")
    ours = isinstance(generator, str) and generator.startswith(REGNF_GENERATOR_PREFIX)
    return "empty" if ours and "noise" not in meta else "unknown"


SPLITS = ("train", "test", "val")
"""Accepted frame splits; frames without one are training frames."""


POSE_RTOL = 1e-5
"""Tolerance of the pose rules, on ``|A^T A / s^2 - I|``, on the last row and on ``|s - 1|``.

Poses stored in float32 are off by about 1e-7; a real scale, shear or skewed rotation is off
by far more than 1e-5, so this refuses every non-rigid pose and no rounding error."""


class CaptureError(RegnfError):
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
        raise RegnfError(f"a similarity must be a real 4x4 matrix ({exc})") from exc
    if M.shape != (4, 4):
        raise RegnfError(f"a similarity must be 4x4, got shape {tuple(M.shape)}")
    if not np.isfinite(M).all():
        raise RegnfError("similarity matrix has non-finite entries")
    if float(np.abs(M[3] - [0.0, 0.0, 0.0, 1.0]).max()) > rtol:
        raise RegnfError(f"the last row of a similarity must be [0, 0, 0, 1], got {M[3].tolist()}")
    A = M[:3, :3]
    det = float(np.linalg.det(A))
    if not 0 < det < math.inf:
        raise RegnfError(
            f"linear part has determinant {det:.6g}, not finite and > 0: a reflection, a negative "
            "scale or a degenerate matrix is not a similarity"
        )
    s = det ** (1.0 / 3.0)
    err = float(np.abs(A.T @ A / (s * s) - np.eye(3)).max())
    if not err <= rtol:  # also refuses NaN (entries so large that A^T A overflows)
        raise RegnfError(
            f"not a uniformly scaled rotation (|A^T A / s^2 - I| = {err:.3g} > {rtol:g}): "
            "non-uniform scale or shear"
        )
    return s


def check_rigid_pose(M: np.ndarray, rtol: float = POSE_RTOL) -> None:
    """Refuse a camera-to-world ``M`` (4, 4) that is not a rotation plus a translation.

    The one rule for camera poses: every capture reader (:mod:`regnf.captures.formats`) and
    rendering (:class:`regnf.render.camera.Camera`) call it, so a pose one accepts the
    other does.

    Raises
    ------
    ValueError
        See :func:`similarity_scale`; or a scale other than 1 (a rotation block scaled by
        7 is a similarity, not a pose).
    """
    s = similarity_scale(M, rtol)
    if abs(s - 1.0) > rtol:
        raise RegnfError(f"must be rigid (scale 1), got scale {s:.6g}")


def check_intrinsics(K: np.ndarray) -> None:
    """Refuse a (3, 3) ``K`` that is not a pinhole matrix with positive focal lengths.

    ``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`` with finite entries and ``fx, fy > 0``
    (which also makes it invertible). Shared by every capture reader and
    :class:`regnf.render.camera.Camera`.

    Raises
    ------
    ValueError
        Wrong shape, non-finite entries, ``fx`` or ``fy`` <= 0, or a lower triangle other
        than ``[0, 0, 1]``.
    """
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RegnfError(f"K must be a real 3x3 matrix ({exc})") from exc
    if K.shape != (3, 3):
        raise RegnfError(f"K must be 3x3, got shape {tuple(K.shape)}")
    if not np.isfinite(K).all():
        raise RegnfError("K has non-finite values")
    fx, fy = float(K[0, 0]), float(K[1, 1])
    if not (fx > 0 and fy > 0):
        raise RegnfError(f"focal lengths must be > 0, got fx = {fx:g}, fy = {fy:g}")
    lower = [float(K[1, 0]), float(K[2, 0]), float(K[2, 1]), float(K[2, 2])]
    if lower != [0.0, 0.0, 0.0, 1.0]:
        raise RegnfError(f"not a pinhole K: K[1, 0], K[2, :] must be 0, [0, 0, 1], got {lower}")


@dataclass
class CaptureFrame:
    """One posed frame of a capture."""

    rgb_path: Path
    """Absolute path of the colour image."""
    depth_path: Path | None
    """Absolute path of the sensor depth (float ``.npy`` or 16-bit PNG), None if absent."""
    camtoworld: np.ndarray
    """(4, 4) float64 OpenCV cam-to-world in the normalised frame."""
    intrinsics: np.ndarray
    """(3, 3) float64 pinhole K; pixel centres at (u + 0.5, v + 0.5)."""
    split: str = "train"
    """``train``, ``test`` or ``val``."""
    mono_depth_path: Path | None = None
    """Absolute path of a monocular depth prior, if the capture has one (unused by regnf)."""
    depth_scale: float = 1.0
    """Normalised units per unit stored in the depth file (1.0: stored normalised)."""
    mask_path: Path | None = None
    """Absolute path of the frame's mask image, if the capture has one (not used yet)."""
    distortion: Distortion | None = None
    """Lens distortion of the frame's camera; None: an ideal pinhole."""
    confidence_path: Path | None = None
    """Absolute path of a per-pixel depth confidence image (ARKit's 0, 1, 2), if the capture has one."""
    rgb_intrinsics: np.ndarray | None = None
    """(3, 3) float64 K of the colour image where its pixel grid is not the depth's (None: the same grid)."""


@dataclass
class Capture:
    """A loaded capture: posed RGB-D frames in a normalised frame plus ground truth."""

    root: Path
    """The capture folder, holding the metadata file :attr:`meta_name`."""
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
    meta_name: str = META_NAME
    """Name of the metadata file in ``root`` (part of the training data's fingerprint)."""
    up: np.ndarray | None = None
    """(3,) unit up direction in the capture's metric world where the format documents one; None: unknown."""
    poses_estimated: bool = False
    """True where the poses are estimates (SLAM, COLMAP, a noisy render), False where they are exact."""
    read_files: list[Path] = field(default_factory=list)
    """Absolute paths of the files the reader read besides :attr:`meta_name` and the frames' images and depth (pose and intrinsics files); part of the training data's fingerprint."""

    @property
    def zero_depth_is_empty(self) -> bool:
        """True where a zero depth means the ray hit nothing, False where it means unknown.

        See :func:`zero_depth_meaning`. Where zeros are unknown, NaN and infinite depth values
        are read as 0 (unknown) too; they are refused otherwise.

        Raises
        ------
        CaptureError
            An invalid :data:`ZERO_DEPTH_KEY`; the message names the metadata file.
        """
        try:
            return zero_depth_meaning(self.meta) == "empty"
        except ValueError as exc:
            raise CaptureError(f"{self.root / self.meta_name}: {exc}") from exc

    @property
    def depth_noise(self) -> DepthNoiseModel | None:
        """The noise model of the capture's depth; None where the depth is exact.

        None where a zero depth means the ray hit nothing (:attr:`zero_depth_is_empty`: regnf's
        own ideal renders), the default :class:`~regnf.captures.depth_uncertainty.DepthNoiseModel`
        (Nguyen et al.'s Kinect) for every other capture; ``regnf.depth_noise`` in the metadata
        overrides it (``"none"``, or an object of the model's fields), as the captures regnf makes
        noisy name their sensor's (:func:`regnf.synthetic.sensor_noise.depth_noise_model`).

        Raises
        ------
        CaptureError
            An invalid ``regnf.depth_noise`` or :data:`ZERO_DEPTH_KEY`; the message names the
            metadata file.
        """
        if DEPTH_NOISE_KEY in self.meta:
            try:
                return parse_depth_noise(self.meta[DEPTH_NOISE_KEY])
            except ValueError as exc:
                raise CaptureError(f"{self.root / self.meta_name}: {exc}") from exc
        return None if self.zero_depth_is_empty else DepthNoiseModel()

    @property
    def scale(self) -> float:
        """Metres per normalised unit (uniform scale of ``worldtogt``)."""
        return float(np.cbrt(abs(np.linalg.det(self.worldtogt[:3, :3]))))

    def rgb(self, i: int) -> np.ndarray:
        """Colour of frame ``i`` as (H, W, 3) float32 in [0, 1], on the capture's pixel grid.

        A frame with :attr:`CaptureFrame.rgb_intrinsics` has its colour on another grid (of any
        size, checked by the reader); it is resampled bilinearly onto the capture's grid
        (:func:`regnf.captures.resample.resample_to_grid`).

        Raises
        ------
        CaptureError
            Unreadable file, a dtype other than uint8 / uint16, or a shape other than
            (H, W), (H, W, 3) or (H, W, 4) (any (h, w) for a colour grid of its own); the
            message names the file and the frame.
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
        K_rgb = self.frames[i].rgb_intrinsics
        if K_rgb is not None and (img.ndim != 3 or img.shape[2] not in (3, 4)):
            # A colour grid of its own: its size was checked by the reader (all frames alike).
            raise CaptureError(f"{where}: image shape {img.shape} is not RGB(A)")
        if K_rgb is None and (img.ndim != 3 or img.shape[:2] != (self.height, self.width) or img.shape[2] not in (3, 4)):
            raise CaptureError(
                f"{where}: image shape {img.shape} does not match {self.height}x{self.width} RGB(A)"
            )
        scale = 65535.0 if img.dtype == np.uint16 else 255.0
        colour = (img[..., :3].astype(np.float32) / np.float32(scale)).astype(np.float32)
        if K_rgb is None:
            return colour
        return resample_to_grid(colour, K_rgb, self.frames[i].intrinsics, self.height, self.width)

    def depth(self, i: int) -> np.ndarray | None:
        """Sensor z-depth of frame ``i``, (H, W) float32 in normalised units; None if absent.

        Raises
        ------
        CaptureError
            Unreadable or pickled file, an 8-bit PNG, a ``.npy`` dtype that is not real
            floating point (complex, integer, bool), a shape other than (H, W), negative
            values, or NaN or infinite ones where zeros mean empty (where they mean unknown
            those read as 0, see :attr:`zero_depth_is_empty`); the message names the file and
            the frame (:func:`regnf.captures.depth_io.read_depth`).
        """
        frame = self.frames[i]
        if frame.depth_path is None:
            return None
        unknown = not self.zero_depth_is_empty
        try:
            return read_depth(frame.depth_path, self.height, self.width, frame.depth_scale, unknown)
        except ValueError as exc:
            raise CaptureError(f"{frame.depth_path}: frame {i}: {exc}") from exc

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
        # Checked inside the folder by the reader; checked again in case meta was edited.
        path = capture_file(self.root, rel, f"{self.root / self.meta_name}: regnf.gt_mesh_path", must_exist=False)
        if not path.is_file():
            return None
        return trimesh.load(path, force="mesh", process=False)


# ----------------------------------------------------------------------------- loading helpers


def parse_matrix(value: Any, shapes: Sequence[tuple[int, ...]], where: str) -> np.ndarray:
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


def read_metadata(meta_path: Path) -> dict:
    """The JSON object in a capture's metadata file ``meta_path`` (absolute).

    Raises
    ------
    CaptureError
        Missing or not a regular file, larger than :data:`MAX_META_BYTES`, not UTF-8 JSON, or
        not a JSON object; the message names ``meta_path``.
    """
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
    return data


def far_plane(centres: np.ndarray) -> float:
    """Far plane of a capture whose scene fills the unit box: farthest camera centre + sqrt(3).

    Parameters
    ----------
    centres : (n, 3) float
        Camera centres in the normalised frame.
    """
    return float(np.max(np.linalg.norm(centres, axis=1)) + np.sqrt(3.0))


def apply_rule(rule: Callable[[np.ndarray], object], value: np.ndarray, where: str) -> None:
    """Apply a pose rule (a function raising ValueError) and name ``where`` if it fails."""
    try:
        rule(value)
    except ValueError as exc:
        raise CaptureError(f"{where}: {exc}") from exc


def pad_pose(mat: np.ndarray) -> np.ndarray:
    """Pad a 3x4 pose with [0, 0, 0, 1]."""
    if mat.shape == (4, 4):
        return mat
    return np.vstack([mat, [0.0, 0.0, 0.0, 1.0]])



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
