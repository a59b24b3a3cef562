"""Clean up a triangle mesh as users have it: CAD exports, scans, triangle soups.

:func:`repair_mesh` merges vertices closer than a tolerance, drops degenerate and duplicate
triangles, makes the winding consistent within each connected piece of surface and turns
every piece outward (positive enclosed volume) unless it is a void inside another piece. It
keeps the order of the surviving faces and the index of the input face each came from (so
per-face colours still line up). It does not fill holes or remove parts: the winding number
(:mod:`regnf.meshes.winding`) copes with those. A mesh that cannot describe a solid at all
raises :class:`MeshError`.

:func:`up_rotation` turns a file's up axis into the library's +Z.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from regnf.core.errors import RegnfError
from regnf.meshes.winding import RayWinding, winding_numbers

MERGE_TOL = 1e-6
"""Vertices closer than this fraction of the bounding-box diagonal are merged. Exporters that
write float32 per-face vertices scatter copies of a vertex by about 1e-7 of the object's
size; 1e-6 welds them and still keeps features of 1 um on a 1 m object."""

VOLUME_TOL = 1e-6
"""A mesh whose enclosed volume is below this fraction of its bounding-box diagonal cubed
encloses nothing (a flat sheet); a 1 mm plate of 1 m x 1 m is at 3.5e-4."""

UP_AXES: tuple[str, ...] = ("z", "y", "x", "-z", "-y", "-x")
"""Up axes a mesh file may use; distillation rotates it to +Z."""


class MeshError(RegnfError):
    """A mesh that cannot be distilled; the message is one line, ``"<source>: <reason>"``.

    Parameters
    ----------
    source : str
        The mesh file (or another name for where the mesh came from).
    reason : str
        What is wrong with it.
    """

    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = " ".join(reason.split())
        super().__init__(f"{source}: {self.reason}")


def up_rotation(up: str) -> np.ndarray:
    """(3, 3) rotation taking axis ``up`` of a file to +Z.

    A signed permutation (exact in floating point): ``y`` and ``-y`` turn about X, so +X
    forward stays +X forward; ``x`` and ``-x`` turn about Y; ``-z`` turns half a turn about X.

    Raises
    ------
    ValueError
        ``up`` is not one of :data:`UP_AXES`.
    """
    rotations = {
        "z": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "y": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],  # (x, y, z) -> (x, -z, y)
        "-y": [[1, 0, 0], [0, 0, 1], [0, -1, 0]],  # (x, y, z) -> (x, z, -y)
        "x": [[0, 0, -1], [0, 1, 0], [1, 0, 0]],  # (x, y, z) -> (-z, y, x)
        "-x": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],  # (x, y, z) -> (z, y, -x)
        "-z": [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
    }
    if up not in rotations:
        raise RegnfError(f"up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
    return np.array(rotations[up], dtype=np.float64)


@dataclass
class RepairReport:
    """What :func:`repair_mesh` found and changed (counts)."""

    faces_in: int
    """Triangles given."""
    merged_vertices: int
    """Vertices welded into another one (closer than the merge tolerance)."""
    degenerate_faces: int
    """Triangles dropped: a repeated corner, thinner than the merge tolerance, or a non-finite corner."""
    duplicate_faces: int
    """Triangles dropped: the same three corners as an earlier one (either winding)."""
    reoriented_faces: int
    """Triangles whose winding was reversed to agree with their neighbours or face outward."""
    inverted_pieces: int
    """Connected pieces turned outward as a whole (their enclosed volume was negative)."""
    cavities: int
    """Inward pieces kept inward: voids inside another piece (see :func:`cavities`)."""
    pieces: int
    """Connected pieces of surface (across edges shared by exactly two triangles)."""
    open_edges: int
    """Edges of one triangle only: the rims of holes and open sheets."""
    nonmanifold_edges: int
    """Edges of three or more triangles."""
    non_orientable_faces: int
    """Triangles of pieces that no winding makes consistent (left as given)."""

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class RepairedMesh:
    """A mesh after :func:`repair_mesh`."""

    vertices: np.ndarray
    """(v, 3) float64, only the vertices the faces use."""
    faces: np.ndarray
    """(f, 3) int64, consistently wound, outward."""
    face_index: np.ndarray
    """(f,) int64: the input face each face is (faces keep their input order)."""
    piece: np.ndarray
    """(f,) int64: the connected piece of each face, 0..pieces-1."""
    report: RepairReport
    """What was found and changed."""

    @property
    def closed(self) -> bool:
        """No open and no non-manifold edges: ray parity alone would already sign it."""
        return self.report.open_edges == 0 and self.report.nonmanifold_edges == 0


def _diagonal(vertices: np.ndarray) -> float:
    return float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0))) if len(vertices) else 0.0


def merge_close_vertices(vertices: np.ndarray, tol: float) -> np.ndarray:
    """(v,) int64 label of each vertex: the lowest index among the vertices within ``tol``
    of it, transitively (pairs from a k-d tree, clusters by connected components)."""
    n = len(vertices)
    if n == 0 or tol <= 0:
        return np.arange(n, dtype=np.int64)
    pairs = cKDTree(vertices).query_pairs(r=tol, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(n, dtype=np.int64)
    graph = scipy.sparse.coo_matrix(
        (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n)
    )
    _, cluster = connected_components(graph, directed=False)
    # Representative: the lowest vertex index of each cluster (its position is kept exactly).
    first = np.full(cluster.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, cluster, np.arange(n, dtype=np.int64))
    return first[cluster]


def _face_areas2(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f,) twice the area of each triangle."""
    tri = vertices[faces]
    return np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def _row_keys(rows: np.ndarray) -> np.ndarray:
    """One int64 (or, for very large indices, void) key per row of small non-negative ints, so
    that ``np.unique`` compares scalars instead of rows (several times faster)."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    n = int(rows.max()) + 1 if rows.size else 1
    if n ** rows.shape[1] < 2**63:
        key = np.zeros(len(rows), dtype=np.int64)
        for j in range(rows.shape[1]):  # over the 2 or 3 columns
            key = key * n + rows[:, j]
        return key
    return rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).reshape(-1)


def _groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equal keys grouped by one stable sort: ``order`` (indices, grouped, each group in input
    order), the group id of each key, and the size of each group (groups in key order)."""
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    start = np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]
    group = np.empty(len(keys), dtype=np.int64)
    group[order] = np.cumsum(start) - 1
    size = np.diff(np.r_[np.flatnonzero(start), len(keys)])
    return order, group, size


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Directed edges (3f, 2) (edge i belongs to face i // 3), the undirected edge id of each
    (3f,), the number of faces of each undirected edge, and the directed edges' indices
    grouped by undirected edge (each group in face order)."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    order, edge_id, count = _groups(_row_keys(np.sort(directed, axis=1)))
    return directed, edge_id, count, order


def orient_pieces(
    faces: np.ndarray, areas: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Consistent winding within each piece of surface joined by two-face edges.

    Every face gets two nodes, as given and reversed; two faces across a manifold edge join
    (as given, as given) and (reversed, reversed) when they traverse the edge in opposite
    directions, (as given, reversed) and (reversed, as given) otherwise. A piece is then two
    mirrored components of that graph, one per consistent winding, and one connected-
    components pass orients every piece at once. Of the two windings, the one that keeps
    more of the piece's area as given is chosen.

    Parameters
    ----------
    faces : (f, 3) int
    areas : (f,) float
        Weights of the majority vote (any positive per-face measure).

    Returns
    -------
    flip : (f,) bool
        Faces to reverse.
    piece : (f,) int64
        Piece of each face, 0..k-1.
    non_orientable : (f,) bool
        Faces of pieces with no consistent winding (never flipped).
    edge_faces : (e,) int64
        Number of faces of each undirected edge (reversing faces does not change it).
    """
    f = len(faces)
    directed, edge_id, count, occ = _edges(faces)
    sorted_ids = edge_id[occ]
    starts = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]])
    two = starts[count[sorted_ids[starts]] == 2]
    e0, e1 = occ[two], occ[two + 1]
    fa, fb = e0 // 3, e1 // 3
    same_direction = directed[e0, 0] == directed[e1, 0]  # the pair disagrees on the winding
    rows = np.concatenate([fa, fa + f])
    cols = np.concatenate([np.where(same_direction, fb + f, fb), np.where(same_direction, fb, fb + f)])
    graph = scipy.sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(2 * f, 2 * f))
    _, label = connected_components(graph, directed=False)
    keep, rev = label[:f], label[f:]
    non_orientable = keep == rev
    flip = keep > rev
    _, piece = np.unique(np.minimum(keep, rev), return_inverse=True)
    piece = piece.reshape(-1).astype(np.int64)
    # Majority vote: reverse the choice in pieces where it would flip most of the area.
    k = int(piece.max()) + 1 if f else 0
    flipped_area = np.bincount(piece, weights=np.where(flip, areas, 0.0), minlength=k)
    total_area = np.bincount(piece, weights=areas, minlength=k)
    invert = flipped_area > 0.5 * total_area
    flip = (flip ^ invert[piece]) & ~non_orientable
    return flip, piece, non_orientable, count


def piece_volumes(vertices: np.ndarray, faces: np.ndarray, piece: np.ndarray) -> np.ndarray:
    """(k,) signed volume enclosed by each piece, about the piece's vertex centroid
    (independent of that point when the piece is closed)."""
    k = int(piece.max()) + 1 if len(piece) else 0
    tri = vertices[faces]
    counts = np.bincount(piece, minlength=k).astype(np.float64)
    centre = np.stack(
        [np.bincount(piece, weights=tri[:, :, j].mean(axis=1), minlength=k) for j in range(3)], axis=1
    ) / np.maximum(counts, 1.0)[:, None]
    rel = tri - centre[piece][:, None, :]
    det = np.einsum("ij,ij->i", rel[:, 0], np.cross(rel[:, 1], rel[:, 2]))
    return np.bincount(piece, weights=det / 6.0, minlength=k)


def cavities(
    vertices: np.ndarray, faces: np.ndarray, piece: np.ndarray, negative: np.ndarray, diag: float
) -> np.ndarray:
    """(k,) bool: the inward pieces that are cavities, not parts turned inside out.

    A piece is a cavity when the six points just beyond the centres of its bounding box's
    sides all lie inside the outward pieces (winding number above 0.5): a void modelled
    with inward normals inside a solid. An inside-out part that pokes out of the solid it
    overlaps, or stands alone, has some of those points outside.
    """
    k = len(negative)
    out = np.zeros(k, dtype=bool)
    if not negative.any() or negative.all():
        return out
    neg = np.flatnonzero(negative)
    lo, hi = piece_boxes(vertices, faces, piece)
    centre = 0.5 * (lo + hi)[neg]
    eps = 1e-3 * diag
    probes = np.repeat(centre[:, None, :], 6, axis=1)  # (m, 6, 3)
    for axis in range(3):
        probes[:, 2 * axis, axis] = hi[neg, axis] + eps
        probes[:, 2 * axis + 1, axis] = lo[neg, axis] - eps
    # Rays are traced in float32: work in units of the diagonal about the mesh's corner.
    origin = vertices.min(axis=0)
    outer = ~negative[piece]
    group = piece_groups(*overlapping_pieces(lo, hi, eps))[piece[outer]]
    outward = RayWinding((vertices - origin) / diag, faces[outer], group)
    w = winding_numbers(outward, (probes.reshape(-1, 3) - origin) / diag).reshape(-1, 6)
    out[neg] = (w > 0.5).all(axis=1)
    return out


def piece_boxes(vertices: np.ndarray, faces: np.ndarray, piece: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) lower and upper corners of each piece's bounding box."""
    k = int(piece.max()) + 1 if len(piece) else 0
    tri = vertices[faces]
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    np.minimum.at(lo, piece, tri.min(axis=1))
    np.maximum.at(hi, piece, tri.max(axis=1))
    return lo, hi


def overlapping_pieces(
    lo: np.ndarray, hi: np.ndarray, pad: float, chunk: int = 1 << 22
) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the other pieces whose boxes, grown by ``pad``, meet each piece's.

    Parameters
    ----------
    lo, hi : (k, 3) float
        Box of each piece.
    pad : float

    Returns
    -------
    offsets : (k + 1,) int64
    partners : (m,) int64
        ``partners[offsets[i]:offsets[i + 1]]`` are the pieces whose boxes meet piece ``i``'s.
    """
    k = len(lo)
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    step = max(1, chunk // max(k, 1))
    for i0 in range(0, k, step):  # chunks of pieces: memory stays at ``chunk`` booleans
        a = slice(i0, min(k, i0 + step))
        hit = ((lo[a, None, :] <= hi[None, :, :] + pad) & (hi[a, None, :] >= lo[None, :, :] - pad)).all(axis=2)
        r, c = np.nonzero(hit)
        r = r + i0
        rows.append(r[r != c])
        cols.append(c[r != c])
    r, c = np.concatenate(rows), np.concatenate(cols)
    offsets = np.zeros(k + 1, dtype=np.int64)
    np.cumsum(np.bincount(r, minlength=k), out=offsets[1:])
    return offsets, c[np.argsort(r, kind="stable")].astype(np.int64)


def piece_groups(offsets: np.ndarray, partners: np.ndarray, seed: int = 0) -> np.ndarray:
    """(k,) int64 colour of each piece, no two overlapping pieces alike (few colours).

    Luby's rounds: each round takes a maximal independent set of the pieces not yet coloured
    (repeatedly, the pieces whose random priority beats every remaining neighbour's) and gives
    it the next colour. Vectorised over the overlap pairs.
    """
    k = len(offsets) - 1
    rows = np.repeat(np.arange(k, dtype=np.int64), np.diff(offsets))
    cols = partners
    prio = np.random.default_rng(seed).permutation(k)
    colour = np.full(k, -1, dtype=np.int64)
    c = 0
    while (colour < 0).any():
        cand = colour < 0
        chosen = np.zeros(k, dtype=bool)
        while cand.any():
            live = cand[rows] & cand[cols]
            best = np.full(k, -1, dtype=np.int64)
            np.maximum.at(best, rows[live], prio[cols[live]])
            pick = cand & (prio > best)
            chosen |= pick
            cand &= ~pick
            cand[cols[pick[rows]]] = False
        colour[chosen] = c
        c += 1
    return colour


def enclosed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by the whole mesh, about its area-weighted centroid."""
    tri = vertices[faces]
    a = _face_areas2(vertices, faces)
    centre = (tri.mean(axis=1) * a[:, None]).sum(axis=0) / max(float(a.sum()), 1e-300)
    rel = tri - centre
    return float(np.einsum("ij,ij->i", rel[:, 0], np.cross(rel[:, 1], rel[:, 2])).sum() / 6.0)


def repair_mesh(
    vertices: np.ndarray, faces: np.ndarray, source: str = "mesh", merge_tol: float = MERGE_TOL
) -> RepairedMesh:
    """Merge, drop degenerate and duplicate faces, orient consistently and outward.

    Parameters
    ----------
    vertices : (v, 3) float
    faces : (f, 3) int
    source : str
        Name of the mesh in error messages (its file).
    merge_tol : float
        Merge distance as a fraction of the bounding-box diagonal.

    Returns
    -------
    RepairedMesh

    Raises
    ------
    MeshError
        No triangles, or none with an area, or nothing enclosed (a flat sheet).
    """
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    Fc = np.asarray(faces, dtype=np.int64).reshape(-1, 3) if np.size(faces) else np.zeros((0, 3), np.int64)
    faces_in = len(Fc)
    if faces_in == 0:
        raise MeshError(source, "the mesh has no triangles (a point cloud or an empty file?)")
    in_range = ((Fc >= 0) & (Fc < len(V))).all(axis=1)
    finite_v = np.isfinite(V).all(axis=1)
    valid = in_range.copy()
    valid[in_range] = finite_v[Fc[in_range]].all(axis=1)
    index = np.flatnonzero(valid)
    Fc = Fc[index]
    # Vertex sets by counting (O(n)), not np.unique (a sort): this is a third of the repair.
    used = np.flatnonzero(np.bincount(Fc.reshape(-1), minlength=len(V)))
    diag = _diagonal(V[used]) if len(used) else 0.0
    if diag == 0.0:
        raise MeshError(source, "the mesh has no triangle with an area (all vertices coincide)")

    # Weld, then compact to the vertices in use (positions of representatives kept exactly).
    rep = np.arange(len(V), dtype=np.int64)
    rep[used] = used[merge_close_vertices(V[used], merge_tol * diag)]
    Fc = rep[Fc]
    merged = len(used) - int(np.count_nonzero(np.bincount(Fc.reshape(-1), minlength=len(V))))

    # Degenerate: a repeated corner, or thinner than the merge tolerance (its smallest height:
    # a sliver between two welded corners and a point on their edge is one, and would
    # otherwise give that edge a third face).
    distinct = (Fc[:, 0] != Fc[:, 1]) & (Fc[:, 1] != Fc[:, 2]) & (Fc[:, 2] != Fc[:, 0])
    area2 = _face_areas2(V, Fc)
    tri = V[Fc]
    longest = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max(axis=1)
    good = distinct & (area2 > merge_tol * diag * np.maximum(longest, 1e-300))
    degenerate = int(faces_in - len(index) + (~good).sum())
    Fc, index, area2 = Fc[good], index[good], area2[good]
    if len(Fc) == 0:
        raise MeshError(source, "the mesh has no triangle with an area (every one is degenerate)")

    # Duplicates (the same corners in any order): keep the first occurrence.
    order, group, _ = _groups(_row_keys(np.sort(Fc, axis=1)))
    first = np.sort(order[np.r_[True, group[order][1:] != group[order][:-1]]])
    duplicates = len(Fc) - len(first)
    Fc, index, area2 = Fc[first], index[first], area2[first]

    flip, piece, non_orientable, count = orient_pieces(Fc, area2)
    Fc = np.where(flip[:, None], Fc[:, ::-1], Fc)
    negative = (piece_volumes(V, Fc, piece) < 0) & (np.bincount(piece, weights=~non_orientable) > 0)
    cavity = cavities(V, Fc, piece, negative, diag)
    inverted = negative & ~cavity
    turn = inverted[piece] & ~non_orientable
    Fc = np.where(turn[:, None], Fc[:, ::-1], Fc)
    reoriented = int((flip ^ turn).sum())

    keep_v = np.bincount(Fc.reshape(-1), minlength=len(V)) > 0
    Fc = (np.cumsum(keep_v) - 1)[Fc]
    V = V[keep_v]
    if abs(enclosed_volume(V, Fc)) < VOLUME_TOL * diag**3:
        raise MeshError(
            source,
            "the mesh encloses no volume (a flat sheet?): its winding number is nowhere above 0.5",
        )
    report = RepairReport(
        faces_in=faces_in,
        merged_vertices=int(merged),
        degenerate_faces=degenerate,
        duplicate_faces=int(duplicates),
        reoriented_faces=reoriented,
        inverted_pieces=int(inverted.sum()),
        cavities=int(cavity.sum()),
        pieces=int(piece.max()) + 1,
        open_edges=int((count == 1).sum()),
        nonmanifold_edges=int((count > 2).sum()),
        non_orientable_faces=int(non_orientable.sum()),
    )
    return RepairedMesh(vertices=V, faces=Fc, face_index=index, piece=piece, report=report)
