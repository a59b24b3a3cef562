"""CLI commands that make data and fields: synth, train, distill, mesh."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from rich.console import Console
from rich.markup import escape

from regnf.captures.formats import read_capture
from regnf.captures.inspection import skipped_note
from regnf.captures.selection import select_frames
from regnf.captures.up_axis import UpChoice, up_line
from regnf.cli.capture_plan import cell_size_warning, plan_training
from regnf.cli.preset_options import preset_options, with_options
from regnf.core.atomic_io import write_bytes
from regnf.core.preflight import (
    PreflightError,
    check_input_file,
    check_mesh_resolution,
    check_output_dir,
    check_output_file,
)
from regnf.fields.field import FieldInfo, Symmetry
from regnf.io.checkpoint import load_field, read_header
from regnf.meshes.mesh_writing import written_rounding
from regnf.meshes.meshing import MESH_FORMATS, extract_mesh, save_mesh
from regnf.synthetic.cache import Cache, capture_info, default_cache_dir
from regnf.synthetic.capture import (
    ObjectCaptureConfig,
    RoomCaptureConfig,
    capture_object,
    capture_room,
)
from regnf.synthetic.library import LIBRARY_NAMES
from regnf.synthetic.rooms import ROOM_NAMES
from regnf.training.distill import DistillConfig
from regnf.training.pose_refinement import pose_refine_line
from regnf.training.presets import (
    OBJECT_MESH,
    OBJECT_RGBD,
    SCENE_RGBD,
    object_mesh_preset,
    object_rgbd_preset,
    scene_rgbd_preset,
)
from regnf.training.training import RGBDTrainConfig

console = Console(stderr=True)

TRAINING_OPTIONS = preset_options(RGBDTrainConfig, {"object": OBJECT_RGBD, "scene": SCENE_RGBD},
                                  skip=("seed", "device", "pose_refine.mode"))
"""``regnf train --training.*``: every training setting, set apart from the command's own options."""

DISTILLATION_OPTIONS = preset_options(DistillConfig, {"mesh": OBJECT_MESH}, skip=("device", "up", "scale"))
"""``regnf distill --distillation.*``: every distillation setting but the units and up axis (``--units``, ``--up``)."""

MESH_WARN_ROUNDING = 1e-3
"""Largest move of a vertex, in metres (field units with --no-world), that ``regnf mesh`` writes without a warning."""



def check_checkpoint_out(out: Path | None) -> None:
    """Refuse, before any work, an ``--out`` that is not a writable ``.safetensors`` file name."""
    if out is not None:
        check_output_file(out, "--out", suffix=".safetensors")


def copy_out(path: Path, out: Path | None) -> None:
    """Copy a cached checkpoint to ``out`` (atomically), if asked (checked by the cache on the way
    in), with the source mesh kept beside it, if any."""
    if out is None:
        return
    from regnf.meshes.source_mesh import source_mesh_file

    source = source_mesh_file(path)
    if source.is_file():
        write_bytes(source_mesh_file(out), source.read_bytes())
    write_bytes(out, path.read_bytes())
    console.print(f"-> {out}")


@dataclass
class Synth:
    """Generate the ONR-like data set: library objects captured in a void, and rooms."""

    names: tuple[str, ...] = ()
    """Objects (c dc fc fc-nop mc et t wt) and/or rooms (ac-room atbl-room mix-room); empty: all
    (the rooms only with a --noise other than ideal)."""
    coverage: Literal["full", "low", "both"] = "both"
    """Room trajectories to capture."""
    out: Path | None = None
    """Write here (one folder per capture) instead of the cache."""
    seed: int = 0
    """Room layout and trajectory seed."""
    noise: Literal["ideal", "sensor", "slam", "harsh"] = "ideal"
    """Sensor and pose noise of the room captures: ideal (none), sensor (depth and colour noise,
    1 mm / 0.05 degree pose jitter), slam (sensor plus a drift reaching 1 cm / 0.3 degree), harsh
    (twice the noise, 10 % speckle, 3 cm / 1 degree drift); true poses go to poses_true.json."""
    noise_seed: int = 0
    """Seed of the sensor and pose noise."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (used when --out is not given)."""

    def run(self) -> None:
        noisy = self.noise != "ideal"
        names = self.names or (ROOM_NAMES if noisy else (*LIBRARY_NAMES, *ROOM_NAMES))
        unknown = [n for n in names if n not in LIBRARY_NAMES and n not in ROOM_NAMES]
        if unknown:
            raise SystemExit(f"unknown object or room {unknown}; choose from {LIBRARY_NAMES + ROOM_NAMES}")
        objects = [n for n in names if n in LIBRARY_NAMES]
        if noisy and objects:
            raise SystemExit(f"--noise {self.noise}: the noise model applies to rooms "
                             f"({' '.join(ROOM_NAMES)}), not to objects {objects}")
        if self.out is not None:
            check_output_dir(self.out)
        cache = Cache(self.cache_dir)
        coverages = ("full", "low") if self.coverage == "both" else (self.coverage,)
        for name in names:
            if name in LIBRARY_NAMES:
                cfg = ObjectCaptureConfig(seed=self.seed)
                cap = capture_object(name, self.out / name, cfg) if self.out else cache.object_capture(name, cfg)
                console.print(f"[green]{name}[/]: {len(cap.frames)} frames in {cap.root}")
                continue
            for cov in coverages:
                cfg = RoomCaptureConfig(coverage=cov, seed=self.seed, noise=self.noise, noise_seed=self.noise_seed)
                # A noisy capture never lands in (or replaces) the ideal capture's folder.
                folder = f"{name}-{cov}" + (f"-{self.noise}-{self.noise_seed}" if noisy else "")
                cap = (
                    capture_room(name, self.out / folder, cfg)
                    if self.out else cache.room_capture(name, cfg)
                )
                console.print(f"[green]{name} ({cov})[/]: {len(cap.frames)} frames, "
                              f"{len(cap.instances)} instances in {cap.root}")


@dataclass
class Train:
    """Train a neural SDF from a posed RGB-D capture (sdfstudio, nerfstudio or ScanNet layout)."""

    capture: Path
    """Capture folder: meta_data.json (ours, or a real sdfstudio / ONR download), a nerfstudio
    transforms.json (Record3D, Polycam, ARKit, COLMAP) or a ScanNet export (color/, depth/,
    pose/, intrinsic/); the format is detected from the folder."""
    capture_format: Literal["auto", "sdfstudio", "nerfstudio", "scannet"] = "auto"
    """Capture layout; auto detects it from the folder's metadata file."""
    out: Path | None = None
    """Also copy the checkpoint here (.safetensors); it is kept in the cache either way."""
    preset: Literal["auto", "object", "scene"] = "auto"
    """Architecture and schedule: a library object or a room seen from inside; auto: the capture's
    metadata says which (regnf's own captures), else scene when most cameras stand inside the
    box of the observed depth, object when they look in from outside (printed, with why)."""
    up: UpChoice = "auto"
    """Up axis of the capture's metric world, recorded in the field (``regnf discover`` uses it);
    auto: the format's convention (regnf's captures, ScanNet: +z), else estimated from the floor
    plane, else from the cameras' mean up vector (printed, with how)."""
    stride: int = 1
    """Train on every N-th training frame."""
    max_frames: int | None = None
    """Train on at most N training frames, evenly spaced (after --stride)."""
    pose_refine: Literal["auto", "on", "off"] = "auto"
    """Refine each training frame's pose jointly with the field (a small rigid correction per
    frame); auto: where the capture's poses are estimates (SLAM, COLMAP, any capture but regnf's
    exact renders). The corrections applied are printed."""
    seed: int = 0
    """Seed of initialisation and sampling (training is deterministic on CPU)."""
    training: TRAINING_OPTIONS = dataclasses.field(default_factory=TRAINING_OPTIONS)
    """Every setting of the training, with its unit; unset: the preset's value (shown as the
    default): for example ``--training.steps 800``, ``--training.pixel-stride 2`` (a quarter of
    the samples), ``--training.w-edge 0``."""
    device: str = "cpu"
    """Torch device, e.g. cpu or cuda."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory: the same data and settings are never trained twice."""

    def run(self) -> None:
        check_checkpoint_out(self.out)
        presets = {"object": object_rgbd_preset, "scene": scene_rgbd_preset}
        candidates = tuple(presets) if self.preset == "auto" else (self.preset,)
        # The settings given are checked against each preset the capture may choose, before any work.
        configs = {p: with_options(presets[p](self.device, self.seed), self.training) for p in candidates}
        select_frames((), self.stride, self.max_frames)  # refuses a bad --stride or --max-frames now
        capture, fmt = read_capture(self.capture, self.capture_format)
        console.print(f"capture {capture.root}: {fmt} format, {len(capture.frames)} frames{skipped_note(capture)}")
        # Before the preset is known, memory is checked at the finer stride either may use.
        pixel_stride = min(c.pixel_stride for c in configs.values())
        plan = plan_training(capture, self.up, self.preset, self.stride, self.max_frames, pixel_stride)
        if len(plan.indices) != len(capture.train_indices()):
            console.print(f"frames: {len(plan.indices)} of {len(capture.train_indices())} training frames")
        console.print(escape(up_line(plan.up)), soft_wrap=True)
        console.print(escape(f"preset: {plan.kind.kind} ({plan.kind.reason})"), soft_wrap=True)
        cfg = configs[plan.kind.kind]
        coarse = cell_size_warning(capture, cfg.architecture.finest_resolution)
        if coarse:
            console.print(f"[yellow]warning[/]: {escape(coarse)}", soft_wrap=True)
        cfg = dataclasses.replace(cfg, pose_refine=dataclasses.replace(cfg.pose_refine, mode=self.pose_refine))
        path = Cache(self.cache_dir).rgbd_field(capture, cfg, plan.indices, plan.up.direction)
        console.print(f"field {capture_info(capture).name!r}: {path}")
        console.print(escape(pose_refine_line(cfg.pose_refine, capture.poses_estimated,
                                              read_header(path)["provenance"].get("pose_refinement"))),
                      soft_wrap=True)
        copy_out(path, self.out)


@dataclass
class Distill:
    """Distil a neural SDF from a mesh (CAD models, scans; need not be watertight)."""

    mesh: Path
    """Input mesh (.ply, .obj, .glb, .stl...), in metres unless --units or --scale says otherwise.
    Holes, open or overlapping parts, flipped or inconsistent winding, duplicate and degenerate
    faces are repaired or tolerated; faces at non-finite vertices are dropped (and counted); a
    mesh that encloses nothing (a flat sheet, a point cloud, a soup of open triangles) is
    refused. Files it names (materials, textures, buffers) are read only from its own folder."""
    units: Literal["m", "cm", "mm"] = "m"
    """Unit of the mesh file's coordinates; they are turned to metres before anything else."""
    scale: float | None = None
    """Metres per unit of the mesh file, for other units (0.0254: inches); instead of --units."""
    out: Path | None = None
    """Also copy the checkpoint here (.safetensors), and the mesh it keeps for other tools beside
    it (``<stem>.source-mesh.safetensors``, read by ``regnf stage new``); the cache keeps both either way."""
    up: Literal["z", "y", "x", "-z", "-y", "-x", "+z", "+y", "+x"] = "z"
    """Up axis of the mesh file; it is turned to +Z, the library's up (y or +y: a Y-up file, as
    many OBJ and glTF exporters write, +X forward kept)."""
    label: str = "object"
    """Semantic class, e.g. chair."""
    name: str = ""
    """Library name; default: the mesh file's stem."""
    symmetry: int = 1
    """Rotational symmetry about +Z: 1 none, k k-fold, 0 continuous."""
    distillation: DISTILLATION_OPTIONS = dataclasses.field(default_factory=DISTILLATION_OPTIONS)
    """Every setting of the distillation, with its unit; unset: the mesh preset's value (shown as
    the default): for example ``--distillation.steps 400``,
    ``--distillation.architecture.finest-resolution 128``."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory: the same mesh and settings are never distilled twice."""

    def run(self) -> None:
        from rich.markup import escape

        from regnf.meshes.mesh_reading import UNITS, extent_warning, load_mesh_file
        from regnf.meshes.mesh_repair import MeshError

        check_input_file(self.mesh, "--mesh", "mesh file")
        check_checkpoint_out(self.out)
        cfg = with_options(object_mesh_preset(self.device), self.distillation)  # checked before any work
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            raise PreflightError(f"--scale {self.scale}: must be a positive number of metres per unit")
        if self.scale is not None and self.units != "m":
            raise PreflightError(f"--units {self.units} and --scale {self.scale}: give one of them")
        scale = UNITS[self.units] if self.scale is None else self.scale
        loaded = load_mesh_file(self.mesh)
        mesh = loaded.mesh
        size = extent_warning(mesh, scale, str(self.mesh), units_given=self.scale is not None or self.units != "m")
        for line in [*loaded.warnings, *([size] if size else [])]:
            console.print(f"[yellow]warning[/]: {escape(line)}", soft_wrap=True)
        cfg = dataclasses.replace(cfg, up=self.up.lstrip("+"), scale=scale)
        units = {"units": self.units} if self.scale is None else {}
        info = FieldInfo(label=self.label, name=self.name or self.mesh.stem, symmetry=Symmetry(self.symmetry),
                         provenance={"mesh": str(self.mesh), **units, "metres_per_unit": scale})
        try:
            path = Cache(self.cache_dir).distilled_field(mesh, info, cfg)
        except (MeshError, PreflightError):
            raise  # already "<file>: <reason>"; the command line prints it on one line
        except ValueError as exc:
            raise SystemExit(f"{self.mesh}: {exc}") from exc
        console.print(f"field {info.name!r}: {path}")
        copy_out(path, self.out)


@dataclass
class Mesh:
    """Extract a coloured mesh from a field checkpoint by marching cubes."""

    field: Path
    """Checkpoint (.safetensors)."""
    out: Path
    """Mesh to write: .ply (float64 vertices) or .glb (float32, relative to an origin when far from zero)."""
    resolution: int = 256
    """Cells along the longest axis of the field's bounds."""
    world: bool = True
    """Write vertices in metres (apply to_world) rather than the field frame."""
    device: str = "cpu"
    """Torch device."""

    def run(self) -> None:
        check_output_file(self.out, "--out")
        if self.out.suffix.lower() not in MESH_FORMATS:
            raise SystemExit(f"--out {self.out}: a mesh is written as one of {', '.join(MESH_FORMATS)}")
        check_mesh_resolution(self.resolution)
        field = load_field(self.field, device=self.device)
        with torch.no_grad():
            mesh = extract_mesh(field, resolution=self.resolution, in_world=self.world)
        save_mesh(mesh, self.out)
        rounding = written_rounding(mesh, MESH_FORMATS[self.out.suffix.lower()])
        if rounding > MESH_WARN_ROUNDING:
            console.print(f"[yellow]warning[/]: {self.out} holds its vertices as float32, which moves them by up "
                          f"to {rounding:.3g} {'m' if self.world else 'field units'}; write a .ply (float64)", soft_wrap=True)
        console.print(f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces -> {self.out}")
