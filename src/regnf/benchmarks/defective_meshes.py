"""Meshes as users have them: known shapes with exact SDFs, damaged in known ways.

Each shape (:data:`SHAPES`) is a clean, watertight mesh in the library's frame (metres, +Z
up, base centred on the origin at z = 0) with an exact analytic field
(:mod:`regnf.fields.analytic`) whose sign is exact everywhere; :func:`defective_mesh` returns
it with one defect of :data:`DEFECTS` applied. The distillation benchmark
(:mod:`regnf.benchmarks.distill`) and the tests (``tests/meshes/test_mesh_sign.py``) share
them. :func:`unsignable_meshes` are inputs no sign can be given to.

Every defect is deterministic for its seed.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from regnf.fields.analytic import Box, Capsule, Union
from regnf.fields.field import Field
from regnf.synthetic.primitives import box as box_part
from regnf.synthetic.primitives import union_parts

SHAPES: tuple[str, ...] = ("box", "capsule", "chair")
"""A 0.8 x 0.5 x 0.3 m box, a capsule 0.7 m tall of radius 0.15 m, a plain chair of 6 boxes."""

DEFECTS: tuple[str, ...] = (
    "clean",
    "holes",
    "flipped",
    "inside-out",
    "duplicates",
    "degenerate",
    "components",
    "decimated",
    "dense",
    "y-up",
    "combined",
)
"""What is wrong with the mesh:

- ``clean``: nothing (the reference row);
- ``holes``: three round patches of faces removed (radius 4 % of the diagonal);
- ``flipped``: a random half of the faces wound the other way;
- ``inside-out``: every face wound the other way;
- ``duplicates``: a second, coincident copy of the whole mesh (its own vertices) and 10 % of
  the faces repeated with the opposite winding;
- ``degenerate``: a triangle soup (every face its own corners, jittered by 1e-8 of the
  diagonal) with 10 % zero-area faces added (repeated corners, collinear corners);
- ``components``: the solid as several overlapping closed parts, not a boolean union;
- ``decimated``: quadric decimation to a quarter of the faces;
- ``dense``: subdivided to about :data:`DENSE_FACES` faces;
- ``y-up``: the clean mesh in a Y-up file (distil it with ``up="y"``);
- ``combined``: holes, flipped faces, duplicates and a jittered soup at once.
"""

BOX_HALF = (0.4, 0.25, 0.15)
CAPSULE_RADIUS = 0.15
CAPSULE_ENDS = ((0.0, 0.0, 0.15), (0.0, 0.0, 0.55))
CHAIR_BOXES: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    *(((0.04, 0.04, 0.44), (x, y, 0.22)) for x in (0.19, -0.19) for y in (0.19, -0.19)),
    ((0.44, 0.44, 0.04), (0.0, 0.0, 0.45)),
    ((0.04, 0.44, 0.42), (-0.20, 0.0, 0.67)),
)
"""(size, centre) in metres of the chair's legs, seat and back; legs poke 1 cm into the seat
and the back sits 1 cm into it, as CAD parts often do."""

MAX_EDGE = 0.015
"""Edges of the clean meshes are at most this fraction of the diagonal, so that a hole is a
round patch of many faces, as in a scan or a tessellated CAD model."""

DENSE_FACES = 300_000
"""Face count of the ``dense`` defect (a large scan)."""

HOLE_RADIUS = 0.04
"""Radius of each hole of ``holes`` and ``combined``, as a fraction of the diagonal."""


@dataclass(frozen=True)
class DefectiveMesh:
    """A shape with one defect."""

    shape: str
    """One of :data:`SHAPES`."""
    defect: str
    """One of :data:`DEFECTS`."""
    mesh: trimesh.Trimesh
    """The damaged mesh, as it would come from a file (``up`` is its up axis)."""
    clean: trimesh.Trimesh
    """The clean watertight mesh, +Z up."""
    field: Field
    """Exact analytic SDF of the shape in metres, +Z up (sign exact everywhere)."""
    up: str
    """Up axis of :attr:`mesh` to give to distillation."""

    @property
    def diagonal(self) -> float:
        """Bounding-box diagonal of the clean mesh, metres."""
        return float(np.linalg.norm(self.clean.extents))


def shape_field(shape: str) -> Field:
    """The exact analytic field of ``shape`` (metres, +Z up)."""
    if shape == "box":
        return Box(half_extents=BOX_HALF, center=(0.0, 0.0, BOX_HALF[2]))
    if shape == "capsule":
        return Capsule(a=CAPSULE_ENDS[0], b=CAPSULE_ENDS[1], radius=CAPSULE_RADIUS)
    if shape == "chair":
        return Union(*(Box(half_extents=np.array(s) / 2, center=c) for s, c in CHAIR_BOXES))
    raise KeyError(f"unknown shape {shape!r}; expected one of {SHAPES}")


def shape_parts(shape: str) -> list[trimesh.Trimesh]:
    """Closed, overlapping parts whose union is ``shape`` (the ``components`` defect)."""
    if shape == "box":
        _, hy, hz = BOX_HALF
        # Two boxes overlapping by 20 cm, and a small part wholly inside (an internal part).
        parts = [((0.5, 2 * hy, 2 * hz), (-0.15, 0.0, hz)), ((0.5, 2 * hy, 2 * hz), (0.15, 0.0, hz)),
                 ((0.2, 0.2, 0.1), (0.0, 0.0, hz))]
        return [_box_mesh(s, c) for s, c in parts]
    if shape == "capsule":
        (_, _, z0), (_, _, z1) = CAPSULE_ENDS
        cyl = trimesh.creation.cylinder(radius=CAPSULE_RADIUS, height=z1 - z0, sections=64)
        cyl.apply_translation((0.0, 0.0, 0.5 * (z0 + z1)))
        ends = []
        for z in (z0, z1):
            s = trimesh.creation.icosphere(subdivisions=4, radius=CAPSULE_RADIUS)
            s.apply_translation((0.0, 0.0, z))
            ends.append(s)
        return [cyl, *ends]
    if shape == "chair":
        return [_box_mesh(s, c) for s, c in CHAIR_BOXES]
    raise KeyError(f"unknown shape {shape!r}; expected one of {SHAPES}")


def _box_mesh(size: tuple[float, ...], centre: tuple[float, ...]) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=np.asarray(size, dtype=np.float64))
    m.apply_translation(np.asarray(centre, dtype=np.float64))
    return m


def _finer(mesh: trimesh.Trimesh, max_edge: float) -> trimesh.Trimesh:
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge, max_iter=20)
    return trimesh.Trimesh(v, f, process=True)


def clean_mesh(shape: str) -> trimesh.Trimesh:
    """The watertight mesh of ``shape``, edges at most :data:`MAX_EDGE` of its diagonal."""
    if shape == "box":
        mesh = _box_mesh(tuple(2 * h for h in BOX_HALF), (0.0, 0.0, BOX_HALF[2]))
    elif shape == "capsule":
        (_, _, z0), (_, _, z1) = CAPSULE_ENDS
        mesh = trimesh.creation.capsule(height=z1 - z0, radius=CAPSULE_RADIUS, count=[48, 48])
        mesh.apply_translation((0.0, 0.0, 0.5 * (z0 + z1)))
    elif shape == "chair":
        mesh = union_parts([box_part(s, c, (0.7, 0.5, 0.3)) for s, c in CHAIR_BOXES], context="chair")
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
    else:
        raise KeyError(f"unknown shape {shape!r}; expected one of {SHAPES}")
    return _finer(mesh, MAX_EDGE * float(np.linalg.norm(mesh.extents)))


def _seed(shape: str, defect: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(f"{shape}/{defect}".encode())])


def cut_holes(mesh: trimesh.Trimesh, rng: np.random.Generator, n: int = 3) -> trimesh.Trimesh:
    """Remove the faces whose centroid is within :data:`HOLE_RADIUS` of ``n`` surface points."""
    centres, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(1 << 31)))
    r = HOLE_RADIUS * float(np.linalg.norm(mesh.extents))
    d = np.linalg.norm(mesh.triangles_center[:, None, :] - centres[None], axis=2).min(axis=1)
    return trimesh.Trimesh(mesh.vertices, mesh.faces[d > r], process=False)


def flip_faces(mesh: trimesh.Trimesh, fraction: float, rng: np.random.Generator) -> trimesh.Trimesh:
    """Reverse the winding of a random ``fraction`` of the faces."""
    f = mesh.faces.copy()
    pick = rng.random(len(f)) < fraction
    f[pick] = f[pick][:, ::-1]
    return trimesh.Trimesh(mesh.vertices, f, process=False)


def add_duplicates(mesh: trimesh.Trimesh, rng: np.random.Generator) -> trimesh.Trimesh:
    """A coincident copy of the whole mesh (own vertices) and 10 % of faces reversed again."""
    v, f = mesh.vertices, mesh.faces
    again = f[rng.random(len(f)) < 0.1][:, ::-1]
    faces = np.concatenate([f, f + len(v), again])
    return trimesh.Trimesh(np.concatenate([v, v]), faces, process=False)


def to_soup(mesh: trimesh.Trimesh, rng: np.random.Generator, degenerate: bool = True) -> trimesh.Trimesh:
    """Every face its own jittered corners (1e-8 of the diagonal), plus 10 % zero-area faces."""
    tri = mesh.triangles.reshape(-1, 3)
    diag = float(np.linalg.norm(mesh.extents))
    tri = tri + rng.normal(0.0, 1e-8 * diag, tri.shape)
    faces = np.arange(len(tri)).reshape(-1, 3)
    if degenerate:
        k = max(1, len(faces) // 20)
        pick = faces[rng.integers(len(faces), size=k)]
        repeated = pick[:, [0, 0, 1]]  # a repeated corner
        mid = 0.5 * (tri[pick[:, 0]] + tri[pick[:, 1]])  # collinear corners: a, b, midpoint
        mids = len(tri) + np.arange(k)
        collinear = np.stack([pick[:, 0], pick[:, 1], mids], axis=1)
        tri = np.concatenate([tri, mid])
        faces = np.concatenate([faces, repeated, collinear])
        faces = faces[rng.permutation(len(faces))]
    return trimesh.Trimesh(tri, faces, process=False)


def decimate(mesh: trimesh.Trimesh, fraction: float = 0.25) -> trimesh.Trimesh:
    """Quadric decimation (Open3D) to ``fraction`` of the faces."""
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces)
    )
    out = legacy.simplify_quadric_decimation(max(64, int(len(mesh.faces) * fraction)))
    return trimesh.Trimesh(np.asarray(out.vertices), np.asarray(out.triangles), process=False)


def densify(mesh: trimesh.Trimesh, faces: int = DENSE_FACES) -> trimesh.Trimesh:
    """Subdivided until it has at least about ``faces`` faces (edges shortened evenly)."""
    edge = float(mesh.edges_unique_length.max())
    # Faces grow as 1 / edge^2, in steps (a face splits in 4 or not at all): try a few edges.
    for factor in (1.0, 0.9, 0.8, 0.7, 0.5):
        dense = _finer(mesh, edge * np.sqrt(len(mesh.faces) / faces) * factor)
        if len(dense.faces) >= 0.9 * faces:
            break
    return dense


Y_UP_FILE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Z-up library frame -> a Y-up file: (x, y, z) -> (x, z, -y) (+X forward kept)."""


def defective_mesh(shape: str, defect: str, seed: int = 0) -> DefectiveMesh:
    """``shape`` with ``defect`` applied (see :data:`DEFECTS`), deterministic for ``seed``."""
    if defect not in DEFECTS:
        raise KeyError(f"unknown defect {defect!r}; expected one of {DEFECTS}")
    clean = clean_mesh(shape)
    rng = _seed(shape, defect, seed)
    up = "z"
    if defect == "clean":
        mesh = clean.copy()
    elif defect == "holes":
        mesh = cut_holes(clean, rng)
    elif defect == "flipped":
        mesh = flip_faces(clean, 0.5, rng)
    elif defect == "inside-out":
        mesh = flip_faces(clean, 1.0, rng)
    elif defect == "duplicates":
        mesh = add_duplicates(clean, rng)
    elif defect == "degenerate":
        mesh = to_soup(clean, rng)
    elif defect == "components":
        diag = float(np.linalg.norm(clean.extents))
        parts = [_finer(p, MAX_EDGE * diag) for p in shape_parts(shape)]
        mesh = trimesh.util.concatenate(parts)
    elif defect == "decimated":
        mesh = decimate(clean)
    elif defect == "dense":
        mesh = densify(clean)
    elif defect == "y-up":
        mesh = trimesh.Trimesh(clean.vertices @ Y_UP_FILE.T, clean.faces, process=False)
        up = "y"
    else:  # combined
        mesh = to_soup(add_duplicates(flip_faces(cut_holes(clean, rng), 0.5, rng), rng), rng)
    return DefectiveMesh(shape, defect, mesh, clean, shape_field(shape), up)


def unsignable_meshes() -> dict[str, trimesh.Trimesh]:
    """Inputs that enclose nothing, by what is wrong with them."""
    sheet = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False
    )
    # A double-sided sheet, as renderers like them: both windings of every face.
    two_sided = trimesh.Trimesh(sheet.vertices, np.concatenate([sheet.faces, sheet.faces[:, ::-1]]),
                                process=False)
    points = trimesh.Trimesh(np.random.default_rng(0).random((50, 3)), np.zeros((0, 3), np.int64),
                             process=False)
    degenerate = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0]],
                                 [[0, 1, 2], [0, 3, 1]], process=False)
    return {"flat sheet": sheet, "two-sided sheet": two_sided, "point cloud": points,
            "degenerate": degenerate}
