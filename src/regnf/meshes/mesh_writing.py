"""Mesh files that keep a vertex where it is: binary PLY in float64, glTF (.glb) placed by a float64 origin.

A mesh in world coordinates may lie far from the origin (a geo-referenced scan sits at 1e5 m
and more). float32 holds 24 bits of mantissa: at 1e5 m a vertex is rounded to 4 mm, at 1e9 m
to 64 m. The PLY file stores its vertices as ``double``. glTF positions are float32 by the
format's rules, so a .glb whose vertices would round by more than :data:`GLB_EXACT`
stores them relative to the centre of their bounding box, and its node places them there with
a float64 translation (the JSON of the node's matrix keeps every digit).
"""

from __future__ import annotations

import os

import numpy as np
import trimesh

GLB_EXACT = 1e-6
"""Largest rounding of a vertex a .glb may make with absolute float32 positions, in the mesh's
units (metres for a world mesh); beyond it the vertices are written relative to an origin."""


def float32_rounding(vertices: np.ndarray, origin: np.ndarray) -> float:
    """Largest distance a vertex moves when stored as float32 relative to ``origin``.

    Parameters
    ----------
    vertices : (N, 3) float64
    origin : (3,) float64

    Returns
    -------
    float
        In the vertices' units; 0 for no vertex.
    """
    if len(vertices) == 0:
        return 0.0
    rel = vertices - origin
    return float(np.abs(rel.astype(np.float32).astype(np.float64) - rel).max())


def glb_origin(vertices: np.ndarray) -> np.ndarray:
    """(3,) float64 origin a .glb stores ``vertices`` (N, 3) relative to: 0 when float32 keeps them
    within :data:`GLB_EXACT`, else the centre of their bounding box."""
    zero = np.zeros(3)
    if len(vertices) == 0 or float32_rounding(vertices, zero) <= GLB_EXACT:
        return zero
    return 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))


def written_rounding(mesh: trimesh.Trimesh, kind: str) -> float:
    """Largest distance a vertex of ``mesh`` moves when written as ``kind`` (``"ply"`` or ``"glb"``)."""
    if kind == "ply":
        return 0.0
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    return float32_rounding(vertices, glb_origin(vertices))


def ply_bytes(mesh: trimesh.Trimesh) -> bytes:
    """Binary little-endian PLY of ``mesh``: double vertices, float normals, RGBA vertex colours if any, int faces."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    colored = mesh.visual.kind == "vertex" and len(mesh.visual.vertex_colors) == len(vertices)
    fields = [("xyz", "<f8", (3,)), ("normal", "<f4", (3,))] + ([("rgba", "u1", (4,))] if colored else [])
    vertex = np.empty(len(vertices), dtype=fields)
    vertex["xyz"] = vertices
    vertex["normal"] = np.asarray(mesh.vertex_normals, dtype=np.float32) if len(faces) else 0.0
    if colored:
        vertex["rgba"] = np.asarray(mesh.visual.vertex_colors, dtype=np.uint8)
    face = np.empty(len(faces), dtype=[("n", "u1"), ("index", "<i4", (3,))])
    face["n"] = 3
    face["index"] = faces
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}",
              *(f"property double {a}" for a in "xyz"), *(f"property float n{a}" for a in "xyz"),
              *([f"property uchar {c}" for c in ("red", "green", "blue", "alpha")] if colored else []),
              f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + vertex.tobytes() + face.tobytes()


def write_ply(mesh: trimesh.Trimesh, path: str | os.PathLike) -> None:
    """Write :func:`ply_bytes` of ``mesh`` to ``path`` (a temporary file the caller renames)."""
    with open(path, "wb") as f:
        f.write(ply_bytes(mesh))
        f.flush()
        os.fsync(f.fileno())


def write_glb(mesh: trimesh.Trimesh, path: str | os.PathLike) -> None:
    """Write ``mesh`` as binary glTF to ``path``, relative to :func:`glb_origin` (placed by its node)."""
    origin = glb_origin(np.asarray(mesh.vertices, dtype=np.float64))
    placed = mesh.copy()
    placed.apply_translation(-origin)
    node = np.eye(4)
    node[:3, 3] = origin
    scene = trimesh.Scene()
    scene.add_geometry(placed, node_name="mesh", geom_name="mesh", transform=node)
    scene.export(path, file_type="glb")
