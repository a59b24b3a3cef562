"""Faces of one part that touch faces of another, and faces split only along those contacts.

Where parts overlap, the solid's surface is what remains of each part's faces outside the
others (:func:`regnf.meshes.mesh_sign.solid_surface`). A face needs splitting only
where another part's surface passes through it: away from those curves a piece of a face is
wholly inside or wholly outside every other closed part, and one winding-number test in front
of it decides. :func:`split_at_contacts` therefore bisects a face only while its pieces touch
a face of another part, so the number of pieces grows with the length of the curves where
parts cut each other, not with the area of the faces inside other parts' boxes.

Contacts are found in two phases, both vectorised over pairs:

- :func:`box_pairs`: pairs of boxes that meet, by hashing the boxes into a uniform grid
  (pairs that share a cell, then deduplicated);
- :func:`touching`: a conservative triangle-triangle test: the boxes meet and neither
  triangle lies wholly on one side of the other's plane (farther than ``pad``). It never
  misses a real contact; a near miss only costs one more bisection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PAIR_CHUNK = 1 << 20
"""Pairs tested at once (bounds the memory of the pair arrays)."""


@dataclass
class FaceSplit:
    """Faces of a mesh near other parts, split into the pieces that are tested for being inside."""

    tested: np.ndarray
    """(t, 3, 3) float64: pieces to test (dropped where the point in front is inside)."""
    tested_parent: np.ndarray
    """(t,) int64: the face each tested piece is (or is a piece of)."""
    kept: np.ndarray
    """(k, 3, 3) float64: pieces kept without a test (away from every other part)."""
    kept_parent: np.ndarray
    """(k,) int64: the face each kept piece is a piece of."""
    split_faces: int
    """Faces that were bisected."""


def cell_size(lo: np.ndarray, hi: np.ndarray, max_cells: int) -> float:
    """Edge of a grid cell such that the boxes (m, 3) ``lo``..``hi`` cover at most ``max_cells``
    cells in all: the median box's largest side, doubled until they fit."""
    ext = (hi - lo).max(axis=1)
    h = max(float(np.median(ext)), 1e-12 * max(float(ext.max()), 1e-300))
    while True:
        span = np.floor(hi / h) - np.floor(lo / h) + 1.0
        if float(span.prod(axis=1).sum()) <= max_cells:
            return h
        h *= 2.0


def box_pairs(lo: np.ndarray, hi: np.ndarray, max_pairs: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Pairs ``(a, b)``, ``a < b``, of boxes that meet (closed boxes: touching counts).

    Parameters
    ----------
    lo, hi : (m, 3) float
        Corners of the boxes.
    max_pairs : int
        Most candidate pairs (box pairs sharing a grid cell) to generate.

    Returns
    -------
    (a, b) : two (p,) int64 arrays, or None
        None when more than ``max_pairs`` candidate pairs share a cell: the boxes pile up too
        much for pair tests to be affordable.
    """
    m = len(lo)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if m < 2:
        return empty
    origin = lo.min(axis=0)
    lo, hi = lo - origin, hi - origin
    h = cell_size(lo, hi, 8 * m + (1 << 20))
    c0 = np.floor(lo / h).astype(np.int64)
    span = np.floor(hi / h).astype(np.int64) - c0 + 1
    count = span.prod(axis=1)
    box = np.repeat(np.arange(m, dtype=np.int64), count)
    local = np.arange(len(box), dtype=np.int64) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[box, 1], span[box, 2]
    cell = c0[box] + np.stack([local // (sy * sz), (local // sz) % sy, local % sz], axis=1)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    box, key = box[order], key[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    size = np.diff(np.r_[start, len(key)])
    # Each entry pairs with the later entries of its cell.
    later = np.repeat(start + size, size) - np.arange(len(key)) - 1
    if int(later.sum()) > max_pairs:
        return None
    ends = np.cumsum(later)
    out_a, out_b = [empty[0]], [empty[1]]
    p0 = 0
    while p0 < len(key):  # chunks of entries with at most PAIR_CHUNK pairs (at least one entry)
        done = int(ends[p0 - 1]) if p0 else 0
        p1 = max(p0 + 1, int(np.searchsorted(ends, done + PAIR_CHUNK, side="right")))
        n = later[p0:p1]
        first = np.repeat(np.arange(p0, p1, dtype=np.int64), n)
        offset = np.arange(len(first), dtype=np.int64) - np.repeat(np.cumsum(n) - n, n)
        a, b = box[first], box[first + 1 + offset]
        meet = ((lo[a] <= hi[b]) & (hi[a] >= lo[b])).all(axis=1) & (a != b)
        out_a.append(np.minimum(a, b)[meet])
        out_b.append(np.maximum(a, b)[meet])
        p0 = p1
    a, b = np.concatenate(out_a), np.concatenate(out_b)
    # A pair of boxes that share several cells was found in each.
    _, first = np.unique(a * m + b, return_index=True)
    return a[first], b[first]


def plane_separates(tri: np.ndarray, normal: np.ndarray, other: np.ndarray, pad: float) -> np.ndarray:
    """(p,) bool: the corners of ``other`` (p, 3, 3) all lie farther than ``pad`` on one side of
    the plane of ``tri`` (p, 3, 3) with unit ``normal`` (p, 3)."""
    d = np.einsum("pkj,pj->pk", other - tri[:, :1], normal)
    return (d > pad).all(axis=1) | (d < -pad).all(axis=1)


def unit_normals(tri: np.ndarray) -> np.ndarray:
    """(t, 3) unit normals of triangles (t, 3, 3) (zero for a degenerate one)."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def touching(
    a: np.ndarray, na: np.ndarray, b: np.ndarray, nb: np.ndarray, pad: float
) -> np.ndarray:
    """(p,) bool: triangles ``a`` and ``b`` (p, 3, 3; unit normals ``na``, ``nb``) may come
    within ``pad`` of each other: their boxes, grown by ``pad``, meet and neither plane
    separates them (a conservative test: true for every real contact)."""
    meet = ((a.min(axis=1) <= b.max(axis=1) + pad) & (a.max(axis=1) >= b.min(axis=1) - pad)).all(axis=1)
    return meet & ~plane_separates(b, nb, a, pad) & ~plane_separates(a, na, b, pad)


def touching_pairs(
    tri_a: np.ndarray, normal_a: np.ndarray, ia: np.ndarray,
    tri_b: np.ndarray, normal_b: np.ndarray, ib: np.ndarray, pad: float,
) -> np.ndarray:
    """(p,) bool: :func:`touching` for the pairs ``(tri_a[ia], tri_b[ib])``, in chunks."""
    out = np.zeros(len(ia), dtype=bool)
    for s in range(0, len(ia), PAIR_CHUNK):
        i, j = ia[s : s + PAIR_CHUNK], ib[s : s + PAIR_CHUNK]
        out[s : s + PAIR_CHUNK] = touching(tri_a[i], normal_a[i], tri_b[j], normal_b[j], pad)
    return out


def longest_edges(tri: np.ndarray) -> np.ndarray:
    """(t,) length of the longest edge of each triangle (t, 3, 3)."""
    return np.stack([np.linalg.norm(tri[:, (j + 1) % 3] - tri[:, j], axis=1) for j in range(3)], axis=1).max(axis=1)


def bisect_longest_edge(tri: np.ndarray) -> np.ndarray:
    """(2t, 3, 3): each triangle of ``tri`` (t, 3, 3) split at the midpoint of its longest
    edge into two with the same winding (children of triangle i at 2i and 2i + 1)."""
    edge_len = np.stack(
        [np.linalg.norm(tri[:, (j + 1) % 3] - tri[:, j], axis=1) for j in range(3)], axis=1
    )
    e = edge_len.argmax(axis=1)
    order = (e[:, None] + np.arange(3)[None, :]) % 3
    a, b, c = (np.take_along_axis(tri, order[:, j, None, None], axis=1)[:, 0] for j in range(3))
    m = 0.5 * (a + b)
    # (a, b, c) with a -> b the longest edge becomes (a, m, c) and (m, b, c).
    return np.stack([np.stack([a, m, c], axis=1), np.stack([m, b, c], axis=1)], axis=1).reshape(-1, 3, 3)


def split_at_contacts(
    tri: np.ndarray,
    piece: np.ndarray,
    cand: np.ndarray,
    pad: float,
    split: float,
    max_pairs: int,
    max_pieces: int,
) -> FaceSplit | None:
    """Split the faces ``cand`` where they touch faces of other pieces, down to ``split``.

    Parameters
    ----------
    tri : (f, 3, 3) float
        Every face of the mesh.
    piece : (f,) int
        Connected piece of each face.
    cand : (c,) int
        Faces whose box meets the box of another, overlapping piece (the only faces that can
        touch another piece's faces).
    pad : float
        Contact distance.
    split : float
        Pieces that touch another piece are bisected until their longest edge is at most this.
    max_pairs, max_pieces : int
        Most candidate face pairs (:func:`box_pairs`) and most pieces of faces (tested and
        bisected, in all) to make.

    Returns
    -------
    FaceSplit or None
        None when either limit would be passed. Every candidate face, or each of its pieces,
        is tested: a piece that touches no other piece is wholly inside or outside each
        other closed part.
    """
    c_tri = tri[cand]
    pairs = box_pairs(c_tri.min(axis=1) - 0.5 * pad, c_tri.max(axis=1) + 0.5 * pad, max_pairs)
    if pairs is None:
        return None
    a, b = cand[pairs[0]], cand[pairs[1]]
    other = piece[a] != piece[b]
    a, b = a[other], b[other]
    normal = np.zeros((len(tri), 3))
    normal[cand] = unit_normals(c_tri)
    hit = touching_pairs(tri, normal, a, tri, normal, b, pad)
    # Each contact in both directions: (face being split, face it touches).
    pair_face = np.concatenate([a[hit], b[hit]])
    pair_other = np.concatenate([b[hit], a[hit]])
    contact = np.zeros(len(tri), dtype=bool)
    contact[pair_face] = True
    alone = cand[~contact[cand]]
    pieces_parent = np.flatnonzero(contact)
    index = np.full(len(tri), -1, dtype=np.int64)
    index[pieces_parent] = np.arange(len(pieces_parent))
    pieces, parent = tri[pieces_parent], pieces_parent
    pair_piece = index[pair_face]
    tested, tested_parent, split_parents = [tri[alone]], [alone], [np.zeros(0, np.int64)]
    made = len(cand)
    while len(pieces):
        short = longest_edges(pieces) <= split
        tested.append(pieces[short])
        tested_parent.append(parent[short])
        long = np.flatnonzero(~short)
        made += 2 * len(long)
        if made > max_pieces:
            return None
        split_parents.append(parent[long])
        children = bisect_longest_edge(pieces[long])
        child_parent = np.repeat(parent[long], 2)
        # The pairs of a bisected piece go to both its children, and are tested again.
        renumber = np.full(len(pieces), -1, dtype=np.int64)
        renumber[long] = np.arange(len(long))
        keep = renumber[pair_piece] >= 0
        cp, co = renumber[pair_piece[keep]], pair_other[keep]
        cp, co = np.concatenate([2 * cp, 2 * cp + 1]), np.concatenate([co, co])
        hit = touching_pairs(children, unit_normals(children), cp, tri, normal, co, pad)
        cp, co = cp[hit], co[hit]
        touches = np.zeros(len(children), dtype=bool)
        touches[cp] = True
        tested.append(children[~touches])
        tested_parent.append(child_parent[~touches])
        renumber = np.cumsum(touches) - 1
        pieces, parent = children[touches], child_parent[touches]
        pair_piece, pair_other = renumber[cp], co
    return FaceSplit(
        tested=np.concatenate(tested),
        tested_parent=np.concatenate(tested_parent),
        kept=np.zeros((0, 3, 3)),
        kept_parent=np.zeros(0, np.int64),
        split_faces=len(np.unique(np.concatenate(split_parents))),
    )
