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
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import trimesh

from synthetic.atomic_io import atomic_path, write_json
from synthetic.instance import Instance

META_NAME = "meta_data.json"
"""File name of the capture's metadata."""

SPLITS = ("train", "test", "val")
"""Accepted frame splits; frames without one are training frames."""


class CaptureError(ValueError):
    """A capture folder is missing, incomplete or malformed; the message names the file."""


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
        """Colour of frame ``i`` as (H, W, 3) float32 in [0, 1]."""
        path = self.frames[i].rgb_path
        try:
            # The extension hint stops imageio from probing every plugin on a corrupt file.
            img = iio.imread(path, extension=path.suffix or None)
        except Exception as exc:  # imageio raises many types for unreadable files
            raise CaptureError(f"{path}: cannot read image ({exc})") from exc
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.ndim != 3 or img.shape[:2] != (self.height, self.width):
            raise CaptureError(
                f"{path}: image shape {img.shape} does not match {self.height}x{self.width}"
            )
        scale = 65535.0 if img.dtype == np.uint16 else 255.0
        return (img[..., :3].astype(np.float32) / np.float32(scale)).astype(np.float32)

    def depth(self, i: int) -> np.ndarray | None:
        """Sensor z-depth of frame ``i``, (H, W) float32 in normalised units; None if absent."""
        path = self.frames[i].depth_path
        if path is None:
            return None
        try:
            depth = np.load(path, allow_pickle=False)
        except Exception as exc:  # corrupt or non-npy file
            raise CaptureError(f"{path}: cannot read depth ({exc})") from exc
        depth = np.squeeze(depth)
        if depth.shape != (self.height, self.width):
            raise CaptureError(
                f"{path}: depth shape {depth.shape} does not match {self.height}x{self.width}"
            )
        if not np.all(np.isfinite(depth)):
            raise CaptureError(f"{path}: depth has non-finite values")
        return depth.astype(np.float32)

    def camtoworld_metres(self, i: int) -> np.ndarray:
        """(4, 4) float64 OpenCV cam-to-world of frame ``i`` in metres (rotation orthonormal)."""
        pose = self.frames[i].camtoworld.copy()
        pose[:3, 3] = self.worldtogt[:3, :3] @ pose[:3, 3] + self.worldtogt[:3, 3]
        return pose

    def train_indices(self) -> list[int]:
        """Indices of training frames."""
        return [i for i, f in enumerate(self.frames) if f.split == "train"]

    def test_indices(self) -> list[int]:
        """Indices of held-out frames (split ``test`` or ``val``)."""
        return [i for i, f in enumerate(self.frames) if f.split != "train"]

    def gt_mesh(self) -> trimesh.Trimesh | None:
        """The ground-truth mesh in metres, or None if the capture has none."""
        rel = self.meta.get("gt_mesh_path")
        if not rel or not (self.root / rel).is_file():
            return None
        return trimesh.load(self.root / rel, force="mesh", process=False)


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


def _existing(root: Path, rel: Any, where: str) -> Path:
    """Resolve a file named in the metadata and check it exists."""
    if not isinstance(rel, str) or not rel:
        raise CaptureError(f"{where} must be a non-empty path string, got {rel!r}")
    path = root / rel
    if not path.is_file():
        raise CaptureError(f"{where}: file {path} not found")
    return path


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
    return CaptureFrame(
        rgb_path=_existing(root, data["rgb_path"], f"{where}.rgb_path"),
        depth_path=None
        if depth_rel is None
        else _existing(root, depth_rel, f"{where}.sensor_depth_path"),
        camtoworld=_to_4x4(_matrix(data["camtoworld"], [(4, 4), (3, 4)], f"{where}.camtoworld")),
        intrinsics=_matrix(data["intrinsics"], [(4, 4), (3, 3)], f"{where}.intrinsics")[
            :3, :3
        ].copy(),
        split=split,
        mono_depth_path=None
        if mono_rel is None
        else _existing(root, mono_rel, f"{where}.mono_depth_path"),
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
        mesh_path=None if not mesh_rel else _existing(root, mesh_rel, f"{where}.mesh_path"),
    )


def load_capture(path: str | Path) -> Capture:
    """Load and validate a capture folder (or its ``meta_data.json``).

    Raises
    ------
    CaptureError
        On a missing folder or file, bad JSON, missing keys, wrong matrix shapes or non-finite
        values; the message names the offending file and entry.
    """
    path = Path(path)
    meta_path = path / META_NAME if path.is_dir() or path.suffix != ".json" else path
    root = meta_path.parent
    if not meta_path.is_file():
        raise CaptureError(f"{meta_path}: file not found (is this a capture folder?)")
    try:
        data = json.loads(meta_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CaptureError(f"{meta_path}: invalid JSON ({exc})") from exc
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
        Placed objects (metres); their ``mesh_path`` is stored relative to ``out_dir``.
    meta : dict, optional
        The ``regnf`` block.
    splits : sequence of str, optional
        Per-frame split; all ``train`` if None.

    Returns
    -------
    Path
        The written ``meta_data.json``.
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
            p = Path(inst.mesh_path).resolve()
            rel = (
                p.relative_to(out.resolve()).as_posix()
                if p.is_relative_to(out.resolve())
                else str(p)
            )
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
