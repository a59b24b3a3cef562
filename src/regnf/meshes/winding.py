"""Generalised winding numbers of triangle meshes: exact sums and ray-sampled estimates.

The generalised winding number (GWN, Jacobson et al. 2013) of a point ``p`` is the sum of
the signed solid angles of the triangles seen from ``p``, divided by 4 pi: 1 inside a closed,
outward-oriented surface, 0 outside, 2 inside two overlapping closed parts, and a smooth
value in between near holes, so that ``w > 0.5`` is an inside test that does not need a
watertight mesh.

Two ways to compute it:

- :func:`exact_winding_numbers`: the sum itself (Van Oosterom and Strackee's formula for the
  solid angle of a triangle), in torch, in chunks of point/triangle pairs. O(points x faces),
  so it is for small meshes, few points and tests (docs/decisions/field-training.md).
- :class:`RayWinding`: the GWN is also the average, over all directions, of the signed
  number of crossings of a ray from ``p`` (+1 where the ray leaves through a face, -1 where
  it enters). Each ray's count is an integer, the same integer for every direction when the
  surface is closed and consistently oriented (however many parts overlap), so a few rays
  give the exact value there; near holes the mean over random directions is an unbiased
  estimate. Rays are traced by Open3D's BVH (Embree), O(log faces) each.

:func:`winding_numbers` combines them: a few rays for every point, and for the points whose
rays disagree (those near holes, or a ray that grazed an edge) the exact sum where it is
affordable, more rays otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch

from regnf.core.errors import RegnfError

FOUR_PI = 4.0 * np.pi


@dataclass
class WindingConfig:
    """How :func:`winding_numbers` estimates the winding number of query points."""

    rays: int = 5
    """Rays per point in the first pass; a point is decided if all agree (docs/decisions/field-training.md)."""
    extra_rays: int = 59
    """Rays added to an undecided point where the exact sum is too costly (docs/decisions/field-training.md)."""
    exact_pairs: int = 8_000_000
    """Most (points x faces) pairs for the exact sum at undecided points (docs/decisions/field-training.md)."""
    seed: int = 0
    """Seed of the random ray directions (results are deterministic for a seed)."""

    def validate(self) -> None:
        """Raise ``ValueError`` for a setting out of range."""
        if self.rays < 1 or self.extra_rays < 0 or self.exact_pairs < 0:
            raise RegnfError(
                f"winding: rays must be >= 1 and extra_rays, exact_pairs >= 0, got "
                f"{self.rays}, {self.extra_rays}, {self.exact_pairs}"
            )


def exact_winding_numbers(
    vertices: np.ndarray,
    faces: np.ndarray,
    points: np.ndarray,
    pair_chunk: int = 1 << 22,
    dtype: torch.dtype = torch.float64,
) -> np.ndarray:
    """Exact generalised winding numbers of ``points`` with respect to a triangle soup.

    Parameters
    ----------
    vertices : (v, 3) float
    faces : (f, 3) int
        Triangles; their winding (counter-clockwise seen from outside) gives the sign.
    points : (n, 3) float
    pair_chunk : int
        Point/triangle pairs evaluated at once (memory: about 100 bytes a pair).
    dtype : torch.dtype
        Precision of the sum.

    Returns
    -------
    (n,) float64
        ``sum_t Omega_t(p) / (4 pi)``.
    """
    V = torch.as_tensor(np.ascontiguousarray(vertices), dtype=dtype)
    Fc = torch.as_tensor(np.ascontiguousarray(faces, dtype=np.int64)).reshape(-1, 3)
    P = torch.as_tensor(np.ascontiguousarray(points), dtype=dtype).reshape(-1, 3)
    out = torch.zeros(P.shape[0], dtype=torch.float64)
    if Fc.shape[0] == 0 or P.shape[0] == 0:
        return out.numpy()
    # Structure of arrays: each coordinate a contiguous (1, f) row broadcast against (n, 1).
    tri = V[Fc]  # (f, 3 corners, 3 coords)
    corners = [[tri[:, k, j].contiguous() for j in range(3)] for k in range(3)]
    face_chunk = max(1, min(Fc.shape[0], pair_chunk))
    point_chunk = max(1, pair_chunk // face_chunk)
    for f0 in range(0, Fc.shape[0], face_chunk):
        c = [[x[f0 : f0 + face_chunk][None, :] for x in k] for k in corners]
        for p0 in range(0, P.shape[0], point_chunk):
            p = P[p0 : p0 + point_chunk]
            px, py, pz = p[:, 0:1], p[:, 1:2], p[:, 2:3]
            ax, ay, az = c[0][0] - px, c[0][1] - py, c[0][2] - pz
            bx, by, bz = c[1][0] - px, c[1][1] - py, c[1][2] - pz
            cx, cy, cz = c[2][0] - px, c[2][1] - py, c[2][2] - pz
            la = torch.sqrt(ax * ax + ay * ay + az * az)
            lb = torch.sqrt(bx * bx + by * by + bz * bz)
            lc = torch.sqrt(cx * cx + cy * cy + cz * cz)
            det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
            den = (
                la * lb * lc
                + (ax * bx + ay * by + az * bz) * lc
                + (bx * cx + by * cy + bz * cz) * la
                + (cx * ax + cy * ay + cz * az) * lb
            )
            # tan(Omega / 2) = det / den (Van Oosterom and Strackee 1983).
            out[p0 : p0 + point_chunk] += (2.0 * torch.atan2(det, den)).sum(dim=1).double()
    return (out / FOUR_PI).numpy()


def random_directions(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float32 unit vectors, uniform on the sphere."""
    d = rng.normal(size=(n, 3))
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    # A zero draw has probability 0; keep it finite anyway.
    d = np.where(norm > 1e-12, d / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))
    return d.astype(np.float32)


class RayWinding:
    """Signed ray-crossing counts against a triangle mesh (Open3D ``RaycastingScene``).

    Open3D reports one hit where a ray meets several triangles of one geometry at the same
    distance (so that a ray through a shared edge counts once), which also merges the
    coincident faces of two overlapping parts (CAD parts often share a face plane) into one
    crossing. Faces are therefore split into ``group`` s, one geometry each, such that
    no two overlapping parts share a group (:func:`regnf.meshes.mesh_repair.piece_groups`).

    Parameters
    ----------
    vertices : (v, 3) float
        In units of order 1 (the scene is float32).
    faces : (f, 3) int
        Consistently oriented triangles (outward normals for an inside-positive count).
    group : (f,) int, optional
        Geometry of each face (default: all in one).
    ray_chunk : int
        Rays traced per call: bounds the memory of the hit lists, which hold every crossing
        (about 40 bytes each, a dozen a ray through a dozen overlapping parts).
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        group: np.ndarray | None = None,
        ray_chunk: int = 1 << 18,
    ) -> None:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        g = np.zeros(len(f), dtype=np.int64) if group is None else np.asarray(group, dtype=np.int64)
        self.n_faces = len(f)
        self.vertices, self.faces = v, f
        self.ray_chunk = ray_chunk
        tri = v[f]
        # Only the sign of direction . normal matters: the unnormalised normal is enough.
        self.normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).astype(np.float32)
        self.scene = o3d.t.geometry.RaycastingScene()
        # Face ids of geometry i are order[start[i]:start[i + 1]]; Open3D numbers geometries
        # 0, 1, ... in the order they are added.
        self._order = np.argsort(g, kind="stable")
        groups, counts = np.unique(g, return_counts=True)
        self._start = np.concatenate([[0], np.cumsum(counts)])
        v32 = o3d.core.Tensor(v.astype(np.float32))
        for i in range(len(groups)):  # one geometry per group: a handful
            ids = self._order[self._start[i] : self._start[i + 1]]
            self.scene.add_triangles(v32, o3d.core.Tensor(f[ids].astype(np.uint32)))

    def crossings(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Signed crossing count of each ray: leaving faces minus entering faces.

        Parameters
        ----------
        origins, directions : (m, 3) float
            One ray each.

        Returns
        -------
        (m,) int64
        """
        m = len(origins)
        out = np.zeros(m, dtype=np.int64)
        if self.n_faces == 0 or m == 0:
            return out
        for r0 in range(0, m, self.ray_chunk):
            o = np.asarray(origins[r0 : r0 + self.ray_chunk], dtype=np.float32)
            d = np.asarray(directions[r0 : r0 + self.ray_chunk], dtype=np.float32)
            hits = self.scene.list_intersections(o3d.core.Tensor(np.concatenate([o, d], axis=1)))
            ray = hits["ray_ids"].numpy().astype(np.int64)
            geometry = hits["geometry_ids"].numpy().astype(np.int64)
            prim = self._order[self._start[geometry] + hits["primitive_ids"].numpy().astype(np.int64)]
            leaving = np.einsum("ij,ij->i", d[ray], self.normals[prim]) > 0
            out[r0 : r0 + len(o)] = np.bincount(ray, weights=np.where(leaving, 1, -1), minlength=len(o))
        return out

    def sample(self, points: np.ndarray, rays: int, rng: np.random.Generator) -> np.ndarray:
        """(n, rays) int64 crossing counts of ``rays`` random directions from each point."""
        p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        dirs = random_directions(len(p) * rays, rng)
        return self.crossings(np.repeat(p, rays, axis=0), dirs).reshape(len(p), rays)


def winding_numbers(
    winding: RayWinding, points: np.ndarray, config: WindingConfig | None = None
) -> np.ndarray:
    """Generalised winding numbers of ``points``: ray-sampled, refined where rays disagree.

    Parameters
    ----------
    winding : RayWinding
        The mesh.
    points : (n, 3) float
    config : WindingConfig, optional

    Returns
    -------
    (n,) float64
        Where every first-pass ray gives the same side, their mean: exact on closed,
        consistently oriented parts (a ray grazing an edge is outvoted); near a hole, a point
        of winding number w is misjudged this way with probability (1 - w)^rays (w^rays
        outside). At the other points the exact sum, or the mean of ``rays + extra_rays``
        ray counts.
    """
    cfg = config or WindingConfig()
    cfg.validate()
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(cfg.seed)
    counts = winding.sample(p, cfg.rays, rng)
    w = counts.mean(axis=1)
    inside_votes = (counts >= 1).sum(axis=1)
    undecided = np.flatnonzero((inside_votes > 0) & (inside_votes < cfg.rays))
    if len(undecided) == 0:
        return w
    if len(undecided) * winding.n_faces <= cfg.exact_pairs:
        w[undecided] = exact_winding_numbers(winding.vertices, winding.faces, p[undecided])
    elif cfg.extra_rays > 0:
        more = winding.sample(p[undecided], cfg.extra_rays, rng)
        w[undecided] = (counts[undecided].sum(axis=1) + more.sum(axis=1)) / (cfg.rays + cfg.extra_rays)
    return w
