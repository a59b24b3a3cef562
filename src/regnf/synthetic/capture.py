"""Render and write the ONR-like captures: library objects in a void, and rooms.

Each capture is an sdfstudio-style folder (see :mod:`regnf.captures.sdfstudio`) plus
``gt_mesh.ply`` (metres) and, for rooms, ``meshes/<instance id>.ply`` (room metres).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from tqdm import tqdm

from regnf.captures.depth_uncertainty import DEPTH_NOISE_KEY
from regnf.captures.instance import Instance
from regnf.captures.metric import SCENE_MARGIN
from regnf.captures.model import Capture, normalisation
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError
from regnf.core.image_io import rgb_to_uint8
from regnf.synthetic.library import make_library_object
from regnf.synthetic.render import VOID_GREY, RGBDRenderer
from regnf.synthetic.rooms import make_room
from regnf.synthetic.sensor_noise import (
    NOISE_LEVELS,
    TRUE_POSES_NAME,
    depth_noise_model,
    noisy_capture_frames,
    write_true_poses,
)
from regnf.synthetic.shading import shaded_copy
from regnf.synthetic.trajectories import (
    object_capture_poses,
    room_full_coverage_poses,
    room_low_coverage_poses,
)

GENERATOR = "regnf.synthetic/2"
"""Recorded in each capture's ``regnf.generator``, and part of its cache key; bump when the
generated data changes (2: depth and instance ids ray-cast at the pixel centres)."""

GT_MESH_NAME = "gt_mesh.ply"
"""Ground-truth mesh file in a capture folder."""


@dataclass(frozen=True)
class ObjectCaptureConfig:
    """How a library object is captured alone, in a grey void, from all around."""

    width: int = 200
    """Image width, pixels."""
    height: int = 200
    """Image height, pixels."""
    focal: float | None = None
    """fx = fy in pixels; None: ``focal_over_width * width``."""
    focal_over_width: float = 1.2
    """Default focal length relative to the width (about 45 degrees horizontal FOV)."""
    n_views: int = 100
    """Number of frames."""
    fill: float = 0.9
    """Fraction of the half-FOV the object's bounding sphere spans (the object: about 55-80 % of the image)."""
    seed: int = 0
    """Recorded for provenance; the object trajectory itself is deterministic."""
    heldout_every: int = 10
    """Every k-th frame is a ``test`` frame; 0 disables held-out frames."""
    margin: float = 1.15
    """Normalisation: s = half the largest bbox extent times this."""
    progress: bool = True
    """Show a tqdm progress bar."""


@dataclass(frozen=True)
class RoomCaptureConfig:
    """How a room is captured: room layout seed, trajectory kind and image format."""

    width: int = 256
    """Image width, pixels."""
    height: int = 192
    """Image height, pixels."""
    focal: float | None = None
    """fx = fy in pixels; None: ``focal_over_width * width``."""
    focal_over_width: float = 0.7
    """Default focal length relative to the width (about 71 degrees horizontal FOV)."""
    n_views: int | None = None
    """Number of frames; None: 120 for full coverage, 30 for low."""
    coverage: str = "full"
    """``full`` (every object from all sides) or ``low`` (a short arc along one side)."""
    seed: int = 0
    """Seed of the room layout and of the trajectory."""
    heldout_every: int = 10
    """Every k-th frame is a ``test`` frame; 0 disables held-out frames."""
    margin: float = SCENE_MARGIN
    """Normalisation: s = half the largest bbox extent times this."""
    progress: bool = True
    """Show a tqdm progress bar."""
    noise: str = "ideal"
    """Sensor and pose noise level: ideal, sensor, slam or harsh (:data:`NOISE_LEVELS`)."""
    noise_seed: int = 0
    """Seed of the sensor and pose noise (unused at ``ideal``)."""

    def frame_count(self) -> int:
        """Frames of the capture: ``n_views``, or 120 for full coverage and 30 for low."""
        return self.n_views or (120 if self.coverage == "full" else 30)


def _intrinsics(
    width: int, height: int, focal: float | None, focal_over_width: float
) -> np.ndarray:
    """(3, 3) float64 pinhole K with the principal point at the image centre."""
    f = float(focal) if focal is not None else focal_over_width * width
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _splits(n: int, every: int) -> list[str]:
    """Frame splits: the k-th, 2k-th, ... frames are held out."""
    return ["test" if every > 0 and (i + 1) % every == 0 else "train" for i in range(n)]


def _export_mesh(mesh: trimesh.Trimesh, path: Path) -> None:
    """Write a mesh atomically (format from the suffix)."""
    with atomic_path(path) as tmp:
        mesh.export(tmp)


def _render_all(
    renderer: RGBDRenderer, poses: np.ndarray, K: np.ndarray, desc: str, progress: bool
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rgbs, depths = [], []
    for pose in tqdm(poses, desc=desc, disable=not progress, leave=False):  # per frame
        out = renderer.render(pose, K)
        rgbs.append(rgb_to_uint8(out.rgb))
        depths.append(out.depth.numpy())
    return rgbs, depths


def capture_object(
    name: str, out_dir: str | Path, config: ObjectCaptureConfig = ObjectCaptureConfig()
) -> Capture:
    """Capture library object ``name`` in a void and write it to ``out_dir``.

    The normalised frame is centred on the object's bbox with scale 1.15 x half its largest
    extent, so each object is trained at its own scale.
    """
    out = Path(out_dir)
    obj = make_library_object(name)
    K = _intrinsics(config.width, config.height, config.focal, config.focal_over_width)
    bounds = obj.mesh.bounds
    centre = bounds.mean(axis=0)
    radius = 0.5 * float(np.linalg.norm(bounds[1] - bounds[0]))
    poses = object_capture_poses(
        centre, radius, config.n_views, K, config.width, config.height, config.fill
    )
    with RGBDRenderer(
        [shaded_copy(obj.mesh)],
        config.width,
        config.height,
        bg_color=VOID_GREY,
        znear=0.05,
        zfar=20.0 * radius + 10.0,
    ) as renderer:
        rgbs, depths = _render_all(renderer, poses, K, f"capture {name}", config.progress)
    _export_mesh(obj.mesh, out / GT_MESH_NAME)
    meta = {
        "kind": "object",
        "name": name,
        "label": obj.label,
        "symmetry": {"axis": "z", "order": obj.symmetry_order},
        "gt_mesh_path": GT_MESH_NAME,
        "seed": config.seed,
        "generator": GENERATOR,
        "config": dataclasses.asdict(config),
    }
    write_capture(
        out,
        rgbs,
        depths,
        poses,
        K,
        normalisation(bounds, config.margin),
        [],
        meta,
        _splits(len(poses), config.heldout_every),
    )
    return load_capture(out)


def capture_room(
    name: str, out_dir: str | Path, config: RoomCaptureConfig = RoomCaptureConfig()
) -> Capture:
    """Generate room ``name`` (layout from ``config.seed``), capture it, write it to ``out_dir``."""
    if config.coverage not in ("full", "low"):
        raise RegnfError(f"capture_room: coverage must be 'full' or 'low', got {config.coverage!r}")
    if config.noise not in NOISE_LEVELS:
        raise RegnfError(f"capture_room: noise must be one of {', '.join(NOISE_LEVELS)}, got {config.noise!r}")
    out = Path(out_dir)
    room = make_room(name, seed=config.seed)
    K = _intrinsics(config.width, config.height, config.focal, config.focal_over_width)
    meshes = room.instance_meshes()
    half = (room.config.size[0] / 2, room.config.size[1] / 2)
    centres = np.array([m.bounds.mean(axis=0) for m in meshes]).reshape(-1, 3)
    radii = np.array([0.5 * np.linalg.norm(m.extents) for m in meshes])
    if config.coverage == "full":
        poses = room_full_coverage_poses(
            half,
            centres,
            radii,
            K,
            config.width,
            config.height,
            n=config.frame_count(),
            seed=config.seed,
        )
    else:
        poses = room_low_coverage_poses(half, centres, n=config.frame_count())
    with RGBDRenderer(
        [shaded_copy(room.mesh), *[shaded_copy(m) for m in meshes]],
        config.width,
        config.height,
        instance_ids=[-1, *range(len(meshes))],
        bg_color=VOID_GREY,
        znear=0.05,
        zfar=50.0,
    ) as renderer:
        rgbs, depths = _render_all(renderer, poses, K, f"capture {name}", config.progress)
    settings = dataclasses.asdict(config)
    noise: dict = {}
    if config.noise == "ideal":
        # An ideal capture's metadata names no noise settings: the fields trained on it are
        # cached under a hash of its bytes, which adding noise options must not change.
        del settings["noise"], settings["noise_seed"]
    else:
        true_poses = poses
        level = NOISE_LEVELS[config.noise]
        rgbs, depths, poses = noisy_capture_frames(rgbs, depths, poses, K, level, config.noise_seed)
        write_true_poses(out, true_poses, config.noise, config.noise_seed)
        noise = {"noise": {"level": config.noise, "seed": config.noise_seed,
                           "true_poses_path": TRUE_POSES_NAME, "config": dataclasses.asdict(level)},
                 DEPTH_NOISE_KEY: dataclasses.asdict(depth_noise_model(level, float(K[0, 0])))}
    instances: list[Instance] = []
    for inst, mesh in zip(room.instances, meshes):
        path = out / "meshes" / f"{inst.id}.ply"
        _export_mesh(mesh, path)
        instances.append(dataclasses.replace(inst, mesh_path=path))
    full = room.full_mesh()
    _export_mesh(full, out / GT_MESH_NAME)
    meta = {
        "kind": "scene",
        "name": name,
        "label": "scene",
        "symmetry": {"axis": "z", "order": 1},
        "gt_mesh_path": GT_MESH_NAME,
        "seed": config.seed,
        "generator": GENERATOR,
        "coverage": config.coverage,
        "config": settings,
        **noise,
    }
    write_capture(
        out,
        rgbs,
        depths,
        poses,
        K,
        normalisation(full.bounds, config.margin),
        instances,
        meta,
        _splits(len(poses), config.heldout_every),
    )
    return load_capture(out)
