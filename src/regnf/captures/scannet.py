"""Reader of the ScanNet export layout (what ScanNet's SensReader writes per scene).

Layout::

    color/0.jpg, 1.jpg, ...          colour (typically 1296x968; .jpg, .jpeg or .png)
    depth/0.png, ...                 uint16 z-depth in millimetres (typically 640x480), 0 = no return
    pose/0.txt, ...                  4x4 camera-to-world, metres, OpenCV camera axes
    intrinsic/intrinsic_depth.txt    4x4, K of the depth camera in the top-left 3x3
    intrinsic/intrinsic_color.txt    4x4, K of the colour camera
    intrinsic/extrinsic_*.txt        optional; must be the identity (colour and depth share a camera)

Frames are the colour files whose stems are integers, in numerical order (0, 1, 2, ..., 10).
The capture's pixel grid is the depth camera's: ``width x height`` of the depth images,
``intrinsics`` the depth K; the colour image keeps its own grid (``rgb_intrinsics``) and
:meth:`regnf.captures.model.Capture.rgb` resamples it onto the depth's. ScanNet writes an
invalid pose (tracking lost) as ``-inf`` (or NaN) entries: such frames are skipped and counted
(``Capture.meta["skipped_frames"]``, their ids in ``meta["skipped_frame_ids"]``). The world is
ScanNet's, +Z up; a zero depth is unknown; the poses are SLAM estimates.

Checked before any depth is read: every colour frame has its depth and pose file, every pose
file holds 4x4 numbers and every finite one is rigid, the intrinsics are pinhole matrices, the
extrinsics (if present) the identity, every colour image has the first one's size. Then each
depth file is read once for the bounds (:mod:`regnf.captures.metric`), which refuses an 8-bit
PNG and a depth in another unit than millimetres.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from regnf.captures.depth_io import read_depth
from regnf.captures.metric import check_median_depth, depth_points, normalise_metric_frames
from regnf.captures.model import (
    POSE_RTOL,
    Capture,
    CaptureError,
    CaptureFrame,
    apply_rule,
    capture_file,
    check_intrinsics,
    check_rigid_pose,
)
from regnf.core.preflight import input_file_problem, open_regular_file

INTRINSIC_DEPTH = "intrinsic/intrinsic_depth.txt"
"""The file that marks a ScanNet export (its metadata file, :attr:`Capture.meta_name`)."""

INTRINSIC_COLOR = "intrinsic/intrinsic_color.txt"
"""Intrinsics of the colour camera."""

EXTRINSICS = ("intrinsic/extrinsic_color.txt", "intrinsic/extrinsic_depth.txt")
"""Optional camera extrinsics; only the identity is accepted."""

COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")
"""Suffixes of colour frames (any case)."""

DEPTH_UNIT = 1e-3
"""Metres per unit of a depth PNG (millimetres)."""

MAX_MATRIX_BYTES = 64 * 2**10
"""Largest pose or intrinsics text file read, in bytes (a 4x4 matrix takes a few hundred)."""

UP = (0.0, 0.0, 1.0)
"""ScanNet's documented up axis in its world."""

_FRAME_STEM = re.compile(r"[0-9]+")


def detect(folder: Path) -> bool:
    """Whether ``folder`` holds ``intrinsic/intrinsic_depth.txt``."""
    return (folder / INTRINSIC_DEPTH).is_file()


def _matrix_file(root: Path, rel: str) -> tuple[Path, np.ndarray]:
    """The file ``rel`` inside ``root`` and the 4x4 matrix of text it holds (non-finite entries kept).

    Raises
    ------
    CaptureError
        Missing, not a regular file, outside the folder, larger than :data:`MAX_MATRIX_BYTES`,
        or not 16 numbers in 4 rows; the message names the file.
    """
    path = capture_file(root, rel, str(root / rel), must_exist=False)
    problem = input_file_problem(path, "file not found")
    if problem is not None:
        raise CaptureError(f"{path}: {problem}")
    try:
        opened = open_regular_file(path)
        if opened is None:
            raise CaptureError(f"{path}: is not a regular file")
        f, size = opened
        with f:
            if size > MAX_MATRIX_BYTES:
                raise CaptureError(f"{path}: {size} bytes, larger than a 4x4 matrix file may be ({MAX_MATRIX_BYTES})")
            text = f.read(MAX_MATRIX_BYTES).decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(f"{path}: cannot be read ({exc})") from exc
    try:
        rows = [[float(x) for x in line.split()] for line in text.splitlines() if line.strip()]
        matrix = np.array(rows, dtype=np.float64)
    except ValueError:
        matrix = None
    if matrix is None or matrix.shape != (4, 4):
        raise CaptureError(f"{path}: expected a 4x4 matrix of numbers (4 rows of 4)")
    return path, matrix


def _intrinsics(root: Path, rel: str) -> tuple[Path, np.ndarray]:
    """The file and pinhole ``K`` (3, 3) of an ``intrinsic_*.txt``."""
    path, M = _matrix_file(root, rel)
    K = M[:3, :3].copy()
    apply_rule(check_intrinsics, K, str(path))
    return path, K


def _frame_files(root: Path) -> list[tuple[int, Path]]:
    """(id, colour file) of every frame in ``color/``, ids in numerical order."""
    folder = root / "color"
    if not folder.is_dir():
        raise CaptureError(f"{folder}: folder not found (a ScanNet export holds color/, depth/, pose/ and intrinsic/)")
    found: dict[int, Path] = {}
    for entry in os.scandir(folder):
        stem, suffix = os.path.splitext(entry.name)
        if suffix.lower() not in COLOR_SUFFIXES or not _FRAME_STEM.fullmatch(stem):
            continue  # not a frame (a thumbnail, a hidden file)
        fid = int(stem)
        if fid in found:
            raise CaptureError(f"{folder}: two colour files for frame {fid}: {found[fid].name} and {entry.name}")
        found[fid] = capture_file(root, f"color/{entry.name}", str(folder / entry.name))
    if not found:
        raise CaptureError(f"{folder}: no colour frames (expected 0.jpg, 1.jpg, ...)")
    return sorted(found.items())


def _required(root: Path, rel: str, colour: Path) -> Path:
    """The file ``rel`` that colour frame ``colour`` needs, checked present and inside ``root``."""
    path = capture_file(root, rel, str(root / rel), must_exist=False)
    if not path.is_file():
        raise CaptureError(f"{path}: file not found (colour frame {colour.name} needs it)")
    return path


def _image_size(path: Path, fid: int) -> tuple[int, int]:
    """(height, width) from an image's header."""
    try:
        shape = iio.improps(path, extension=path.suffix or None).shape
    except Exception as exc:  # imageio raises many types for unreadable files
        raise CaptureError(f"{path}: frame {fid}: cannot read image ({exc})") from exc
    if len(shape) < 2:
        raise CaptureError(f"{path}: frame {fid}: not an image (shape {tuple(shape)})")
    return int(shape[0]), int(shape[1])


def read(path: str | Path) -> Capture:
    """Read and check a ScanNet export folder.

    Raises
    ------
    CaptureError
        One line naming the file: a missing ``color/`` or no colour frame, a colour frame
        without its depth or pose file, a pose file that is not 4x4 numbers, a finite pose
        that is not rigid, every pose invalid, a bad intrinsics file, extrinsics other than
        the identity, a colour image that cannot be read or has another size than the first,
        a depth file :func:`regnf.captures.depth_io.read_depth` refuses (an 8-bit PNG, a size
        other than the first depth image's...), or a median depth beyond
        :data:`~regnf.captures.metric.MAX_MEDIAN_DEPTH_M` (not millimetres).
    """
    root = Path(os.path.abspath(path))
    if not detect(root):
        raise CaptureError(f"{root / INTRINSIC_DEPTH}: file not found (is this a ScanNet export folder?)")
    _, K_depth = _intrinsics(root, INTRINSIC_DEPTH)  # the metadata file: hashed as meta_name
    color_file, K_color = _intrinsics(root, INTRINSIC_COLOR)
    read_files = [color_file]
    for rel in EXTRINSICS:
        if not (root / rel).exists():
            continue
        ext_path, E = _matrix_file(root, rel)
        if not np.isfinite(E).all() or float(np.abs(E - np.eye(4)).max()) > POSE_RTOL:
            raise CaptureError(
                f"{ext_path}: extrinsics other than the identity are not supported (colour and depth "
                "must share a camera)"
            )
        read_files.append(ext_path)

    frames, skipped = [], []
    for fid, colour in _frame_files(root):
        stem = os.path.splitext(colour.name)[0]
        depth = _required(root, f"depth/{stem}.png", colour)
        _required(root, f"pose/{stem}.txt", colour)
        pose_path, pose = _matrix_file(root, f"pose/{stem}.txt")
        read_files.append(pose_path)
        if not np.isfinite(pose).all():
            skipped.append(fid)  # tracking lost: ScanNet writes -inf
            continue
        apply_rule(check_rigid_pose, pose, str(pose_path))
        frames.append(CaptureFrame(rgb_path=colour, depth_path=depth, camtoworld=pose, intrinsics=K_depth,
                                   depth_scale=DEPTH_UNIT, rgb_intrinsics=K_color))
    if not frames:
        raise CaptureError(f"{root / 'pose'}: all {len(skipped)} poses are invalid (non-finite entries); no frame to use")

    colour_size = _image_size(frames[0].rgb_path, 0)
    for i, fr in enumerate(frames[1:], 1):
        size = _image_size(fr.rgb_path, i)
        if size != colour_size:
            raise CaptureError(
                f"{fr.rgb_path}: frame {i}: colour image is {size[1]}x{size[0]} pixels, frame 0 "
                f"({frames[0].rgb_path.name}) is {colour_size[1]}x{colour_size[0]}: all must be the same size"
            )
    height, width = _image_size(frames[0].depth_path, 0)

    points = []
    for i, fr in enumerate(frames):
        try:
            depth_m = read_depth(fr.depth_path, height, width, DEPTH_UNIT)
        except ValueError as exc:
            raise CaptureError(f"{fr.depth_path}: frame {i}: {exc}") from exc
        check_median_depth(depth_m, f"{fr.depth_path}: frame {i}",
                           "read as millimetres: is the depth in millimetres, as ScanNet writes it?")
        points.append(depth_points(depth_m, K_depth, fr.camtoworld))
    worldtogt, scene_box = normalise_metric_frames(frames, np.concatenate(points))
    meta = {"format": "scannet", "skipped_frames": len(skipped), "skipped_frame_ids": skipped}
    return Capture(root, width, height, frames, worldtogt, scene_box, [], meta, INTRINSIC_DEPTH,
                   up=np.array(UP), poses_estimated=True, read_files=read_files)
