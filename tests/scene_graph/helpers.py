"""Tiny checkpoints, box proxies standing on z = 0, and registration results for the tests."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import torch
import trimesh

from regnf.fields.field import FieldInfo, Symmetry
from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig
from regnf.io.checkpoint import save_field
from regnf.scene_graph import new_stage

TINY = NeuralSDFConfig(levels=2, finest_resolution=16, hidden_dim=16, base_resolution=8,
                       geo_feature_dim=3, color_hidden_dim=8)

# name -> (class, symmetry order, box size in metres: its proxy)
OBJECTS = {
    "c": ("chair", 1, (0.44, 0.44, 0.88)),
    "dc": ("chair", 1, (0.50, 0.46, 1.00)),
    "fc-nop": ("chair", 1, (0.80, 0.75, 0.90)),
    "fc": ("chair", 1, (0.80, 0.75, 1.00)),
    "t": ("table", 1, (1.40, 0.80, 0.74)),
    "wt": ("table", 0, (0.90, 0.90, 0.72)),
}


def similarity(yaw: float, t: tuple[float, float, float], s: float, tilt: float = 0.0) -> np.ndarray:
    """(4, 4) ``T R S`` with R = Rz(yaw) Rx(tilt), by hand."""
    cz, sz, cx, sx = math.cos(yaw), math.sin(yaw), math.cos(tilt), math.sin(tilt)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]])
    Rx = np.array([[1.0, 0, 0], [0, cx, -sx], [0, sx, cx]])
    M = np.eye(4)
    M[:3, :3] = s * (Rz @ Rx)
    M[:3, 3] = t
    return M


def checkpoint(folder: Path, name: str, label: str, symmetry: int = 1, scale: float = 0.6,
               seed: int = 0) -> Path:
    """A tiny NeuralSDF checkpoint (a blob of radius ~0.5 field units) with metadata."""
    torch.manual_seed(seed)
    to_world = torch.eye(4, dtype=torch.float64)
    to_world[:3, :3] *= scale
    to_world[2, 3] = 0.5 * scale  # base near z = 0 in the canonical frame
    info = FieldInfo(label=label, name=name, symmetry=Symmetry(symmetry),
                     provenance={"made_by": "tests", "seed": seed, "nested": {"a": [1, 2.5, None]}})
    field = NeuralSDF(TINY, to_world=to_world, info=info)
    path = folder / f"{name}.safetensors"
    save_field(field, path)
    return path


def box_proxy(size: tuple[float, float, float]) -> trimesh.Trimesh:
    """A box standing on z = 0, centred on the Z axis, with vertex colours."""
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation([0.0, 0.0, size[2] / 2])
    colors = np.tile(np.array([[200, 120, 40, 255]], dtype=np.uint8), (len(mesh.vertices), 1))
    mesh.visual.vertex_colors = colors
    return mesh


def make_library(folder: Path, names: tuple[str, ...]) -> tuple[Path, list[Path], dict]:
    """Checkpoints for a scene and ``names``, and box proxies for all of them."""
    src = folder / "src"
    src.mkdir(parents=True, exist_ok=True)
    scene = checkpoint(src, "room", "scene", scale=3.0)
    libs = [checkpoint(src, n, OBJECTS[n][0], OBJECTS[n][1], seed=i + 1) for i, n in enumerate(names)]
    proxies = {n: box_proxy(OBJECTS[n][2]) for n in names}
    floor = trimesh.creation.box(extents=(6.0, 5.0, 0.1))
    floor.apply_translation([0.0, 0.0, -0.05])
    proxies["scene"] = floor
    return scene, libs, proxies


def make_stage(folder: Path, names: tuple[str, ...] = ("c", "dc", "t"), suffix: str = ".usda") -> Path:
    """A new stage with box proxies (no marching cubes: fast)."""
    scene, libs, proxies = make_library(folder, names)
    path = folder / "stage" / f"scene{suffix}"
    new_stage(path, scene, libs, proxies=proxies, provenance={"test": "yes", "n": 3, "f": 0.25,
                                                              "flag": True, "sub": {"k": "v"}})
    return path


def registration_json(library_name: str, library_field: Path, M: np.ndarray, accepted: bool = True,
                      confidence: float = 0.93) -> dict:
    """A result shaped like ``regnf register --out`` writes (only what the stage uses, plus extras)."""
    T = np.linalg.inv(M)  # any similarity will do for the provenance record
    return {
        "method": "regnf",
        "transform_scene_to_library": {"matrix": T.tolist()},
        "confidence": confidence,
        "accepted": accepted,
        "losses": {"final_loss": 0.0123, "mean_residual": 0.000456},
        "timings": {"sampling": 1.5, "initialisation": 2.25, "refinement": 3.0, "total": 6.75},
        "thresholds": {"inlier_threshold": 0.01, "acceptance_threshold": 0.5},
        "proposal_box": {"center": [1.0, 2.0, 0.4], "half_extents": [0.3, 0.3, 0.45],
                         "rotation": np.eye(3).tolist()},
        "hypotheses": [],
        "history": [],
        "scene_field": "scene.safetensors",
        "library_field": str(library_field),
        "library_name": library_name,
        "library_label": OBJECTS[library_name][0],
        "object_to_scene_metres": M.tolist(),
    }


def snapshot(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file (or "dir") under ``folder``, hidden ones included."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
        for p in sorted(folder.rglob("*"))
    }
