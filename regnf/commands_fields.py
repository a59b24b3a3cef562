"""CLI commands that make data and fields: synth, train, distill, mesh."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from rich.console import Console

from regnf.core.atomic_io import write_bytes
from regnf.core.preflight import (
    check_input_file,
    check_mesh_resolution,
    check_output_dir,
    check_output_file,
)
from regnf.neural_fields.cache import Cache, capture_info, default_cache_dir
from regnf.neural_fields.checkpoint import load_field
from regnf.neural_fields.field import FieldInfo, Symmetry
from regnf.neural_fields.meshing import MESH_FORMATS, extract_mesh, save_mesh
from regnf.neural_fields.presets import object_mesh_preset, object_rgbd_preset, scene_rgbd_preset
from regnf.synthetic.capture import (
    ObjectCaptureConfig,
    RoomCaptureConfig,
    capture_object,
    capture_room,
)
from regnf.synthetic.library import LIBRARY_NAMES
from regnf.synthetic.rooms import ROOM_NAMES
from regnf.synthetic.sdfstudio_format import load_capture

console = Console(stderr=True)



def check_checkpoint_out(out: Path | None) -> None:
    """Refuse, before any work, an ``--out`` that is not a writable ``.safetensors`` file name."""
    if out is not None:
        check_output_file(out, "--out", suffix=".safetensors")


def copy_out(path: Path, out: Path | None) -> None:
    """Copy a cached checkpoint to ``out`` (atomically), if asked (checked by the cache on the way in)."""
    if out is None:
        return
    write_bytes(out, path.read_bytes())
    console.print(f"-> {out}")


@dataclass
class Synth:
    """Generate the ONR-like data set: library objects captured in a void, and rooms."""

    names: tuple[str, ...] = ()
    """Objects (c dc fc fc-nop mc et t wt) and/or rooms (ac-room atbl-room mix-room); empty: all."""
    coverage: Literal["full", "low", "both"] = "both"
    """Room trajectories to capture."""
    out: Path | None = None
    """Write here (one folder per capture) instead of the cache."""
    seed: int = 0
    """Room layout and trajectory seed."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (used when --out is not given)."""

    def run(self) -> None:
        names = self.names or (*LIBRARY_NAMES, *ROOM_NAMES)
        unknown = [n for n in names if n not in LIBRARY_NAMES and n not in ROOM_NAMES]
        if unknown:
            raise SystemExit(f"unknown object or room {unknown}; choose from {LIBRARY_NAMES + ROOM_NAMES}")
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
                cfg = RoomCaptureConfig(coverage=cov, seed=self.seed)
                cap = (
                    capture_room(name, self.out / f"{name}-{cov}", cfg)
                    if self.out else cache.room_capture(name, cfg)
                )
                console.print(f"[green]{name} ({cov})[/]: {len(cap.frames)} frames, "
                              f"{len(cap.instances)} instances in {cap.root}")


@dataclass
class Train:
    """Train a neural SDF from a posed RGB-D capture (sdfstudio meta_data.json layout)."""

    capture: Path
    """Folder holding meta_data.json (ours, or a real sdfstudio / ONR download)."""
    out: Path | None = None
    """Also copy the checkpoint here (.safetensors); it is kept in the cache either way."""
    preset: Literal["object", "scene"] = "object"
    """Architecture and schedule: a library object or a room seen from inside."""
    steps: int | None = None
    """Override the preset's number of optimisation steps."""
    edge_weight: float | None = None
    """Override the preset's weight of the occluding-edge loss (0: off; the room preset uses 1,
    the object preset 0; ``RGBDTrainConfig.w_edge`` gives what it does on the rooms)."""
    outline_weight: float | None = None
    """Override the preset's weight of the outline loss, the edge loss's counterpart on the
    occluders' side (0: off; the room preset uses 1, the object preset 0;
    ``RGBDTrainConfig.w_outline`` gives what it does on the rooms: the low-coverage
    registration back to 11 of 11, and floaters)."""
    carve_every: int | None = None
    """Override the preset's steps between the floater pool's mining passes (0: no pool; the
    room preset uses 50, the object preset 0; ``RGBDTrainConfig.carve_every``)."""
    seed: int = 0
    """Seed of initialisation and sampling (training is deterministic on CPU)."""
    device: str = "cpu"
    """Torch device, e.g. cpu or cuda."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory: the same data and settings are never trained twice."""

    def run(self) -> None:
        check_checkpoint_out(self.out)
        if self.steps is not None and self.steps < 1:
            raise SystemExit(f"--steps must be at least 1, got {self.steps}")
        if self.edge_weight is not None and not (math.isfinite(self.edge_weight) and self.edge_weight >= 0):
            raise SystemExit(f"--edge-weight must be a finite number >= 0, got {self.edge_weight}")
        if self.outline_weight is not None and not (math.isfinite(self.outline_weight) and self.outline_weight >= 0):
            raise SystemExit(f"--outline-weight must be a finite number >= 0, got {self.outline_weight}")
        if self.carve_every is not None and self.carve_every < 0:
            raise SystemExit(f"--carve-every must be at least 0, got {self.carve_every}")
        capture = load_capture(self.capture)
        preset = object_rgbd_preset if self.preset == "object" else scene_rgbd_preset
        cfg = preset(self.device, self.seed)
        if self.steps is not None:
            cfg = dataclasses.replace(cfg, steps=self.steps)
        if self.edge_weight is not None:
            cfg = dataclasses.replace(cfg, w_edge=self.edge_weight)
        if self.outline_weight is not None:
            cfg = dataclasses.replace(cfg, w_outline=self.outline_weight)
        if self.carve_every is not None:
            cfg = dataclasses.replace(cfg, carve_every=self.carve_every)
        path = Cache(self.cache_dir).rgbd_field(capture, cfg)
        console.print(f"field {capture_info(capture).name!r}: {path}")
        copy_out(path, self.out)


@dataclass
class Distill:
    """Distil a neural SDF from a mesh in metres (CAD models, scans; need not be watertight)."""

    mesh: Path
    """Input mesh (.ply, .obj, .glb, .stl...) in metres. Holes, open or overlapping parts, flipped
    or inconsistent winding, duplicate and degenerate faces are repaired or tolerated; a mesh
    that encloses nothing (a flat sheet, a point cloud) is refused."""
    out: Path | None = None
    """Also copy the checkpoint here (.safetensors); it is kept in the cache either way."""
    up: Literal["z", "y", "x", "-z", "-y", "-x"] = "z"
    """Up axis of the mesh file; it is turned to +Z, the library's up (y: a Y-up file, as many
    OBJ and glTF exporters write, +X forward kept)."""
    label: str = "object"
    """Semantic class, e.g. chair."""
    name: str = ""
    """Library name; default: the mesh file's stem."""
    symmetry: int = 1
    """Rotational symmetry about +Z: 1 none, k k-fold, 0 continuous."""
    steps: int | None = None
    """Override the number of optimisation steps."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory: the same mesh and settings are never distilled twice."""

    def run(self) -> None:
        import trimesh

        from regnf.neural_fields.mesh_repair import MeshError

        check_input_file(self.mesh, "--mesh", "mesh file")
        check_checkpoint_out(self.out)
        if self.steps is not None and self.steps < 1:
            raise SystemExit(f"--steps must be at least 1, got {self.steps}")
        try:
            mesh = trimesh.load(self.mesh, force="mesh")
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise SystemExit(f"{self.mesh}: cannot read mesh ({exc})") from exc
        cfg = dataclasses.replace(object_mesh_preset(self.device), up=self.up)
        if self.steps is not None:
            cfg = dataclasses.replace(cfg, steps=self.steps)
        info = FieldInfo(label=self.label, name=self.name or self.mesh.stem,
                         symmetry=Symmetry(self.symmetry), provenance={"mesh": str(self.mesh)})
        try:
            path = Cache(self.cache_dir).distilled_field(mesh, info, cfg)
        except MeshError:
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
    """Mesh to write (.ply or .glb)."""
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
        console.print(f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces -> {self.out}")
