"""Signed distances to a mesh that need not be watertight.

Distance and sign come from two surfaces:

- the sign from the generalised winding number of the whole repaired mesh (inside where it
  is above 0.5; :mod:`regnf.meshes.winding`), which is right across holes (the 0.5 level
  spans them like a soap film), inside overlapping parts (2 > 0.5) and for open pieces;
- the unsigned distance (Open3D ``compute_distance``, any triangle soup) from the mesh
  without its internal faces: where parts overlap, as CAD assemblies and scans stitched
  from several shells do, a face of one part inside another is not on the solid's surface,
  and distances to it would put a false zero inside the solid. A face is internal when the
  point just in front of it is inside (winding number above 0.5); faces that cross into
  another part are bisected first, so that only their inner pieces go. Splitting near other
  parts' boxes costs the area of the faces there; where that is too costly (large faces of
  many overlapping parts, triangle soups), faces are split only along the curves where they
  touch another part's faces (:mod:`regnf.meshes.face_contacts`), and a mesh whose
  faces cut through each other too often even for that is refused.

:class:`SignedMesh` holds both, in the frame its vertices are given in (distillation uses the
field frame, about [-1, 1]^3).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from regnf.core.errors import RegnfError
from regnf.meshes.face_contacts import (
    FaceSplit,
    bisect_longest_edge,
    longest_edges,
    split_at_contacts,
)
from regnf.meshes.mesh_repair import MeshError, overlapping_pieces, piece_boxes, piece_groups
from regnf.meshes.winding import RayWinding, WindingConfig, winding_numbers


@dataclass
class MeshSignConfig:
    """How :class:`SignedMesh` signs distances and finds internal faces."""

    winding: WindingConfig = field(default_factory=WindingConfig)
    """Winding-number estimation (rays, exact refinement)."""
    split_edge: float = 0.01
    """Bisect faces reaching into another part to this edge, fraction of the diagonal (docs/decisions/mesh-signs.md)."""
    front_offset: float = 1e-4
    """Test offset in front of a face for being internal, fraction of the diagonal (docs/decisions/mesh-signs.md)."""
    box_pairs: int = 1_000_000
    """Most (face piece, other part) box tests when splitting near parts' boxes; past it, split at contacts only."""
    contact_pairs: int = 4_000_000
    """Most candidate face pairs of the splitting at contacts; past it the mesh is refused."""
    contact_pieces: int = 1_000_000
    """Most pieces of faces the splitting at contacts makes; past it the mesh is refused."""

    def validate(self) -> None:
        """Raise ``ValueError`` for a setting out of range."""
        self.winding.validate()
        if min(self.box_pairs, self.contact_pairs, self.contact_pieces) < 0:
            raise RegnfError(f"sign: the limits must be >= 0, got {self.box_pairs}, {self.contact_pairs}, "
                             f"{self.contact_pieces}")
        if not (0 < self.split_edge <= 1 and 0 < self.front_offset < self.split_edge):
            raise RegnfError(
                f"sign: need 0 < front_offset < split_edge <= 1, got {self.front_offset}, {self.split_edge}"
            )


def reaches_other_piece(
    tri: np.ndarray,
    piece: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    offsets: np.ndarray,
    partners: np.ndarray,
    pad: float,
    chunk: int = 1 << 22,
) -> np.ndarray:
    """(t,) bool: triangles ``tri`` (t, 3, 3) whose box meets the box of a piece overlapping
    their own ``piece`` (t,)."""
    out = np.zeros(len(tri), dtype=bool)
    n_partners = offsets[piece + 1] - offsets[piece]
    cand = np.flatnonzero(n_partners > 0)
    t_lo, t_hi = tri.min(axis=1), tri.max(axis=1)
    # Pairs (triangle, partner piece), in chunks of triangles so memory stays bounded.
    ends = np.cumsum(n_partners[cand])
    start = 0
    while start < len(cand):
        done_before = ends[start - 1] if start else 0
        stop = int(np.searchsorted(ends, done_before + chunk, side="right"))
        stop = max(stop, start + 1)
        c = cand[start:stop]
        reps = n_partners[c]
        tri_of_pair = np.repeat(c, reps)
        first = np.repeat(offsets[piece[c]], reps)
        within = np.arange(len(tri_of_pair)) - np.repeat(np.cumsum(reps) - reps, reps)
        other = partners[first + within]
        hit = ((t_lo[tri_of_pair] <= hi[other] + pad) & (t_hi[tri_of_pair] >= lo[other] - pad)).all(axis=1)
        out[np.unique(tri_of_pair[hit])] = True
        start = stop
    return out


@dataclass
class Surface:
    """The faces that bound the solid: a triangle soup for distances and surface samples."""

    vertices: np.ndarray
    """(v, 3) float64."""
    faces: np.ndarray
    """(f, 3) int64."""
    parent: np.ndarray
    """(f,) int64: the face of the repaired mesh each face is (or is a piece of)."""
    internal_faces: int
    """Faces or pieces dropped as internal."""
    split_faces: int
    """Faces of the repaired mesh that were bisected (they reached into another part)."""


def split_near_boxes(
    tri: np.ndarray,
    piece: np.ndarray,
    cand: np.ndarray,
    boxes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    pad: float,
    split: float,
    max_pairs: int,
) -> FaceSplit | None:
    """Bisect the faces ``cand`` while their pieces' boxes meet another overlapping piece's box.

    Pieces longer than ``split`` are bisected and their children tested again, until every
    candidate piece is short; a child away from every other piece's box is kept untested.

    Parameters
    ----------
    tri : (f, 3, 3) float
    piece : (f,) int
    cand : (c,) int
        Faces whose box meets another overlapping piece's box.
    boxes : (lo, hi, offsets, partners)
        Boxes of the pieces and the CSR lists of overlapping pieces
        (:func:`regnf.meshes.mesh_repair.overlapping_pieces`).
    pad, split : float
    max_pairs : int
        Most (piece of a face, overlapping piece) box tests to make.

    Returns
    -------
    FaceSplit or None
        None as soon as the next round of box tests would pass ``max_pairs``.
    """
    lo, hi, offsets, partners = boxes
    n_partners = offsets[1:] - offsets[:-1]
    pieces, parent = tri[cand], cand
    test_tri, test_parent, free_tri, free_parent, split_parents = [], [], [], [], []
    pairs = 0
    while len(pieces):
        short = longest_edges(pieces) <= split
        test_tri.append(pieces[short])
        test_parent.append(parent[short])
        split_parents.append(parent[~short])
        child_parent = np.repeat(parent[~short], 2)
        pairs += int(n_partners[piece[child_parent]].sum())
        if pairs > max_pairs:
            return None
        children = bisect_longest_edge(pieces[~short])
        near = reaches_other_piece(children, piece[child_parent], lo, hi, offsets, partners, pad)
        # A piece away from every other part's box cannot be inside it: kept untested.
        free_tri.append(children[~near])
        free_parent.append(child_parent[~near])
        pieces, parent = children[near], child_parent[near]
    return FaceSplit(
        tested=np.concatenate(test_tri),
        tested_parent=np.concatenate(test_parent),
        kept=np.concatenate(free_tri),
        kept_parent=np.concatenate(free_parent),
        split_faces=len(np.unique(np.concatenate(split_parents))),
    )


def solid_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    piece: np.ndarray,
    winding: RayWinding,
    config: MeshSignConfig,
    source: str = "mesh",
) -> Surface:
    """The mesh without the faces (and pieces of faces) that lie inside another part.

    Only faces whose box meets the box of another, overlapping piece are candidates; they are
    split into short pieces near the other parts (:func:`split_near_boxes`, or where that
    would pass :attr:`MeshSignConfig.box_pairs`, only along the curves where they touch
    another part's faces: :func:`regnf.meshes.face_contacts.split_at_contacts`); a
    tested piece is dropped when the point ``front_offset`` in front of its centroid has a
    winding number above 0.5. One piece, no candidates: the mesh as it is.

    Parameters
    ----------
    vertices : (v, 3) float
    faces : (f, 3) int
        Consistently oriented, outward (:func:`regnf.meshes.mesh_repair.repair_mesh`).
    piece : (f,) int
        Connected piece of each face.
    winding : RayWinding
        Of the same mesh.
    config : MeshSignConfig
    source : str
        The mesh's file, for error messages.

    Raises
    ------
    MeshError
        Its parts cut through each other along too many faces for either way of splitting
        (:attr:`MeshSignConfig.contact_pairs`, :attr:`MeshSignConfig.contact_pieces`).
    """
    V = np.asarray(vertices, dtype=np.float64)
    Fc = np.asarray(faces, dtype=np.int64)
    keep_all = Surface(V, Fc, np.arange(len(Fc), dtype=np.int64), 0, 0)
    k = int(piece.max()) + 1 if len(piece) else 0
    if k <= 1:
        return keep_all
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    pad = config.front_offset * diag
    tri = V[Fc]
    lo, hi = piece_boxes(V, Fc, piece)
    offsets, partners = overlapping_pieces(lo, hi, pad)
    cand = np.flatnonzero(reaches_other_piece(tri, piece, lo, hi, offsets, partners, pad))
    if len(cand) == 0:
        return keep_all
    split = config.split_edge * diag
    parts = split_near_boxes(tri, piece, cand, (lo, hi, offsets, partners), pad, split, config.box_pairs)
    if parts is None:
        parts = split_at_contacts(tri, piece, cand, pad, split, config.contact_pairs, config.contact_pieces)
    if parts is None:
        raise MeshError(source, f"{len(cand)} of its {len(Fc)} faces reach into other parts, and they cut "
                                "through each other too often to find the solid's surface (more than "
                                f"{config.contact_pairs} face pairs or {config.contact_pieces} pieces of faces); "
                                "is it a triangle soup rather than a solid?")
    tested = parts.tested
    normal = np.cross(tested[:, 1] - tested[:, 0], tested[:, 2] - tested[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    internal = winding_numbers(winding, tested.mean(axis=1) + pad * normal, config.winding) > 0.5
    kept_tri = np.concatenate([tested[~internal], parts.kept])
    kept_parent = np.concatenate([parts.tested_parent[~internal], parts.kept_parent])
    whole = np.ones(len(Fc), dtype=bool)
    whole[cand] = False
    soup = len(V) + np.arange(3 * len(kept_tri), dtype=np.int64).reshape(-1, 3)
    return Surface(
        vertices=np.concatenate([V, kept_tri.reshape(-1, 3)]),
        faces=np.concatenate([Fc[whole], soup]),
        parent=np.concatenate([np.flatnonzero(whole), kept_parent]),
        internal_faces=int(internal.sum()),
        split_faces=parts.split_faces,
    )


class SignedMesh:
    """Signed distances to a repaired mesh: winding-number sign, distance to the solid's surface.

    Parameters
    ----------
    vertices : (v, 3) float
        Units of order 1 (Open3D traces float32).
    faces : (f, 3) int
        Consistently oriented and outward (:func:`regnf.meshes.mesh_repair.repair_mesh`).
    piece : (f,) int
        Connected piece of each face.
    config : MeshSignConfig, optional
    source : str
        The mesh's file, for error messages.

    Raises
    ------
    MeshError
        See :func:`solid_surface`.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        piece: np.ndarray,
        config: MeshSignConfig | None = None,
        source: str = "mesh",
    ) -> None:
        self.config = config or MeshSignConfig()
        self.config.validate()
        V = np.asarray(vertices, dtype=np.float64)
        Fc = np.asarray(faces, dtype=np.int64)
        piece = np.asarray(piece, dtype=np.int64)
        lo, hi = piece_boxes(V, Fc, piece)
        pad = self.config.front_offset * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
        self.winding = RayWinding(V, Fc, piece_groups(*overlapping_pieces(lo, hi, pad))[piece])
        check_bounds_a_solid(self.winding, V, self.config.winding.rays, source)
        self.surface = solid_surface(V, Fc, piece, self.winding, self.config, source)
        self._distance = o3d.t.geometry.RaycastingScene()
        self._distance.add_triangles(
            o3d.core.Tensor(self.surface.vertices.astype(np.float32)),
            o3d.core.Tensor(self.surface.faces.astype(np.uint32)),
        )

    def winding_numbers(self, points: np.ndarray) -> np.ndarray:
        """(n,) float64 generalised winding numbers of ``points`` (n, 3)."""
        return winding_numbers(self.winding, points, self.config.winding)

    def unsigned_distance(self, points: np.ndarray) -> np.ndarray:
        """(n,) float32 distance of ``points`` (n, 3) to the solid's surface."""
        p = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        return self._distance.compute_distance(p).numpy()

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (negative inside) and winding number of ``points`` (n, 3).

        Returns
        -------
        sdf : (n,) float32
        winding : (n,) float64
        """
        d = self.unsigned_distance(points)
        w = self.winding_numbers(points)
        return np.where(w > 0.5, -d, d).astype(np.float32), w


SOLID_PROBES = 4096
"""Points in a mesh's box at which :func:`check_bounds_a_solid` casts its rays."""
MIN_DECIDED_INSIDE = 0.1
"""Of the probe points some ray finds inside, at least this share must be inside for every ray
(the defective meshes with holes: 0.6-0.95; a box missing two of its six sides: 0.28; a soup of
150 random triangles: 0.02)."""


def check_bounds_a_solid(winding: RayWinding, vertices: np.ndarray, rays: int, source: str, seed: int = 0) -> None:
    """Refuse a mesh whose faces bound no solid before its costly steps (a soup of open faces).

    Rays from points spread through the mesh's box: where some ray says inside and another
    outside, the point is near a hole. A solid, even one with holes, is inside for every ray
    through much of its inside; in a soup of open triangles almost no point is, and there
    every winding number would need the costly refinement of :func:`winding_numbers`.

    Parameters
    ----------
    winding : RayWinding
    vertices : (v, 3) float
        The mesh's vertices (for its box).
    rays : int
        Rays per point.
    source : str
        The mesh's file, for the message.
    seed : int

    Raises
    ------
    MeshError
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    rng = np.random.default_rng(seed)
    points = lo + rng.random((SOLID_PROBES, 3)) * (hi - lo)
    votes = (winding.sample(points, rays, rng) >= 1).sum(axis=1)
    some, every = int((votes > 0).sum()), int((votes == rays).sum())
    if rays > 1 and some > 0 and every < MIN_DECIDED_INSIDE * some:
        raise MeshError(source, f"its faces bound no solid: rays from {100 * (some - every) / SOLID_PROBES:.0f} % of "
                                "the points in its box disagree on whether they are inside, and almost none are "
                                "inside for every ray (a soup of open triangles?)")


def check_signable(winding: np.ndarray, source: str) -> None:
    """Refuse a mesh whose winding number, at points spread through its bounds, is above 0.5
    nowhere or everywhere: it does not separate an inside from an outside.

    Parameters
    ----------
    winding : (n,) float
        Winding numbers at points drawn uniformly in (and a little beyond) the mesh's box.
    source : str
        The mesh's file, for the message.

    Raises
    ------
    MeshError
    """
    inside = np.asarray(winding) > 0.5
    if not inside.any():
        raise MeshError(source, "the mesh encloses no volume: its winding number is nowhere above 0.5 "
                                "(an open sheet or a surface with large holes?)")
    if inside.all():
        raise MeshError(source, "the mesh has no outside: its winding number is above 0.5 everywhere "
                                "in and around its bounds")
