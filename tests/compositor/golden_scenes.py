"""The scenes of the golden-image tests: analytic furniture in a room, and one tiny neural field.

Everything is first built in METRES (canonical object frames: base centred at the origin,
z = 0, +Z up) and then put into field frames by hand, independently of the code under test:

- the scene field is the room with a table and a chair placed by their ``object_to_scene``
  poses, expressed in a scene field frame whose ``to_world`` ``S`` rotates about Z, shifts
  and scales by 1.6;
- every library field is its object in a normalised frame of its own (``to_world`` ``L``,
  one of them rotated), built as ``Transformed(object_metres, inv(L), to_world=L)``.

So a library object substituted with the right frames (``inv(S) O L``) lands exactly where
the scene's copy is. The library colours differ from the scene's (each object was "captured"
on its own), so a substitution shows.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from regnf.compositor import Camera, CompositeField, look_at
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.compositor.substitution import SubstitutedInstance, build_composite
from regnf.fields.analytic import Box, Cylinder, Transformed, Union
from regnf.fields.field import Field, FieldInfo
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.fields.similarity import similarity_matrix

GOLDEN_DIR = Path(__file__).parent / "golden"
"""Where the golden PNGs (and the tiny neural checkpoint) live."""
WIDTH, HEIGHT = 96, 72
"""Size of every golden image."""


def sim(yaw_deg: float, t: tuple[float, float, float], s: float, axis: str = "z") -> np.ndarray:
    """(4, 4) similarity: rotation about ``axis`` by ``yaw_deg``, translation ``t``, scale ``s``."""
    return similarity_matrix(Rotation.from_euler(axis, yaw_deg, degrees=True).as_matrix(), t, s)


# -- frames ---------------------------------------------------------------------------------
S = sim(25.0, (0.2, -0.1, 0.3), 1.6)
"""Scene field frame -> room metres (rotation about Z only: +Z stays up)."""
O_TABLE = sim(20.0, (0.35, 0.3, 0.0), 1.0)
"""Table: canonical metres -> room metres."""
O_CHAIR = sim(125.0, (-0.55, -0.35, 0.0), 1.1)
"""Chair: canonical metres -> room metres (10 % larger than the library chair)."""
L_TABLE_A = sim(0.0, (0.0, 0.0, 0.37), 0.55)
L_CHAIR_A = sim(0.0, (0.0, 0.0, 0.5), 0.6)
L_TABLE_B = sim(0.0, (0.0, 0.0, 0.36), 0.5)
L_CHAIR_B = sim(40.0, (0.0, 0.0, 0.4), 0.5)
"""Library field frames -> canonical metres (chair b's frame is rotated)."""


# -- objects in canonical metres -------------------------------------------------------------
def table_a(top: tuple, legs: tuple) -> Field:
    """Rectangular table, 0.9 x 0.6 x 0.74 m."""
    parts = [Box((0.45, 0.3, 0.025), (0.0, 0.0, 0.715), color=top)]
    parts += [Box((0.03, 0.03, 0.345), (x, y, 0.345), color=legs) for x in (-0.38, 0.38) for y in (-0.24, 0.24)]
    return Union(*parts, label="table", name="table_a")


def chair_a(color: tuple) -> Field:
    """Plain chair: seat at 0.45 m, back towards -x."""
    parts = [Box((0.22, 0.22, 0.03), (0.0, 0.0, 0.45), color=color),
             Box((0.03, 0.22, 0.28), (-0.19, 0.0, 0.76), color=color)]
    parts += [Box((0.025, 0.025, 0.21), (x, y, 0.21), color=color) for x in (-0.18, 0.18) for y in (-0.18, 0.18)]
    return Union(*parts, label="chair", name="chair_a")


def chair_b() -> Field:
    """Armchair: a block, a back and two arms."""
    c = (0.25, 0.6, 0.3)
    return Union(
        Box((0.35, 0.35, 0.2), (0.0, 0.0, 0.2), color=c),
        Box((0.08, 0.35, 0.35), (-0.27, 0.0, 0.55), color=(0.2, 0.45, 0.25)),
        Box((0.3, 0.06, 0.12), (0.0, 0.29, 0.52), color=c),
        Box((0.3, 0.06, 0.12), (0.0, -0.29, 0.52), color=c),
        label="chair", name="chair_b",
    )


def table_b() -> Field:
    """Round pedestal table."""
    c = (0.85, 0.8, 0.7)
    return Union(
        Cylinder(0.42, 0.02, (0.0, 0.0, 0.7), color=c),
        Cylinder(0.06, 0.34, (0.0, 0.0, 0.34), color=(0.3, 0.3, 0.3)),
        Cylinder(0.25, 0.02, (0.0, 0.0, 0.02), color=(0.3, 0.3, 0.3)),
        label="table", name="table_b",
    )


def in_frame(obj: Field, L: np.ndarray, name: str) -> Field:
    """``obj`` (metres) as a library field with ``to_world = L``."""
    return Transformed(obj, np.linalg.inv(L), label=obj.label, name=name, to_world=L)


# -- the scene --------------------------------------------------------------------------------
SCENE_CHAIR_COLOR = (0.2, 0.35, 0.8)
SCENE_TABLE_TOP, SCENE_TABLE_LEGS = (0.7, 0.45, 0.25), (0.45, 0.28, 0.15)
LIB_CHAIR_COLOR = (0.85, 0.3, 0.2)
LIB_TABLE_TOP, LIB_TABLE_LEGS = (0.9, 0.75, 0.4), (0.6, 0.5, 0.3)


def scene_field(match_library: bool = False) -> Field:
    """The room in the scene field frame; ``match_library`` colours it like the library."""
    to_field = np.linalg.inv(S)
    chair = chair_a(LIB_CHAIR_COLOR if match_library else SCENE_CHAIR_COLOR)
    table = table_a(*((LIB_TABLE_TOP, LIB_TABLE_LEGS) if match_library else (SCENE_TABLE_TOP, SCENE_TABLE_LEGS)))
    floor = Box((1.6, 1.4, 0.05), (0.0, 0.0, -0.05), color=(0.55, 0.57, 0.6))
    wall = Box((1.6, 0.05, 0.6), (0.0, 1.35, 0.6), color=(0.88, 0.86, 0.8))
    return Union(
        Transformed(floor, to_field),
        Transformed(wall, to_field),
        Transformed(table, to_field @ O_TABLE),
        Transformed(chair, to_field @ O_CHAIR),
        label="scene", name="golden_room", to_world=S,
    )


@dataclass(frozen=True)
class Library:
    """The library fields, in their own frames."""

    table_a: Field
    chair_a: Field
    table_b: Field
    chair_b: Field


def library() -> Library:
    return Library(
        table_a=in_frame(table_a(LIB_TABLE_TOP, LIB_TABLE_LEGS), L_TABLE_A, "table_a"),
        chair_a=in_frame(chair_a(LIB_CHAIR_COLOR), L_CHAIR_A, "chair_a"),
        table_b=in_frame(table_b(), L_TABLE_B, "table_b"),
        chair_b=in_frame(chair_b(), L_CHAIR_B, "chair_b"),
    )


def substituted(lib: Library, table: Field, chair: Field) -> list[SubstitutedInstance]:
    """Instance 1 the table, 2 the chair (registered as table_a / chair_a), showing ``table`` and ``chair``."""
    return [
        SubstitutedInstance(1, table, lib.table_a, O_TABLE, name="table_1"),
        SubstitutedInstance(2, chair, lib.chair_a, O_CHAIR, name="chair_1"),
    ]


def composite(shown: str, config: StageCompositeConfig, match_library: bool = False) -> CompositeField:
    """The golden composites: ``shown`` is ``own`` (substitution), ``other`` (replacement) or ``neural``."""
    lib = library()
    scene = scene_field(match_library)
    if shown == "own":
        specs = substituted(lib, lib.table_a, lib.chair_a)
    elif shown == "other":
        specs = substituted(lib, lib.table_b, lib.chair_b)
    elif shown == "neural":
        specs = substituted(lib, lib.table_a, neural_pouf())
    else:
        raise ValueError(f"unknown substitution {shown!r}")
    return build_composite(scene, specs, config)


def camera() -> Camera:
    """The golden view of the room: from the front right, above the table."""
    return Camera.from_fov(WIDTH, HEIGHT, 62.0, look_at((2.1, -2.0, 1.7), (-0.05, 0.0, 0.35)))


def neural_camera() -> Camera:
    """A close view of the neural pouf alone (its canonical metres)."""
    return Camera.from_fov(WIDTH, HEIGHT, 50.0, look_at((0.9, -0.7, 0.7), (0.0, 0.0, 0.2)))


# -- the tiny neural field ---------------------------------------------------------------------
NEURAL_ARCH = NeuralSDFConfig(levels=2, features_per_level=2, base_resolution=8, finest_resolution=16,
                              hidden_dim=32, geo_feature_dim=4, color_hidden_dim=16)
"""Small enough to keep in the repository (a few tens of kB)."""


def pouf_mesh() -> trimesh.Trimesh:
    """A cylinder pouf in canonical metres (base at z = 0): red sides, light top and bottom."""
    mesh = trimesh.creation.cylinder(radius=0.25, height=0.42, sections=48)
    mesh.apply_translation((0.0, 0.0, 0.21))
    up = np.abs(mesh.face_normals[:, 2]) > 0.9
    colors = np.where(up[:, None], [[240, 200, 120, 255]], [[200, 40, 40, 255]]).astype(np.uint8)
    mesh.visual.face_colors = colors
    return mesh


def distil(mesh: trimesh.Trimesh, name: str, label: str, steps: int = 300) -> Field:
    """A tiny field distilled from ``mesh``: about 10 s, on one thread so that it is
    deterministic for its seed (bitwise-identical weights run after run; trained fields are
    never committed)."""
    from regnf.training.distill import DistillConfig, distill_mesh

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = DistillConfig(steps=steps, batch=2048, pool_surface=20000, seed=0, architecture=NEURAL_ARCH)
        field, _ = distill_mesh(mesh, cfg, info=FieldInfo(label=label, name=name), progress=False)
    finally:
        torch.set_num_threads(threads)
    return field


def distil_pouf(steps: int = 300) -> Field:
    """Distil the pouf (:func:`distil`)."""
    return distil(pouf_mesh(), "pouf", "chair", steps)


def distilled_library(folder: Path) -> list[Path]:
    """Checkpoints of the pouf (a chair) and a crate (a table, 0.6 x 0.4 x 0.35 m standing on
    z = 0), distilled here into ``folder``."""
    from regnf.io.checkpoint import save_field

    crate = trimesh.creation.box(extents=(0.6, 0.4, 0.35))
    crate.apply_translation((0.0, 0.0, 0.175))
    paths = []
    for name, label, mesh in (("pouf", "chair", pouf_mesh()), ("crate", "table", crate)):
        paths.append(folder / f"{name}.safetensors")
        save_field(distil(mesh, name, label), paths[-1])
    return paths


@functools.lru_cache(maxsize=1)
def neural_pouf() -> Field:
    """The tiny neural field, distilled once per process."""
    return distil_pouf()
