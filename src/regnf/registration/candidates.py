"""Object candidates in a scene field, with no boxes given: its surface, less the room's
support planes (floor, walls, ceiling), in connected groups, each with an upright box.

The first step of discovery: every candidate is a proposal box that registration can take as
it takes a data set's box. Everything is measured in scene metres (the field's ``to_world``);
the boxes are returned in metres and in the scene field's frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.meshes.meshing import extract_mesh


@dataclass(frozen=True)
class CandidateConfig:
    """Settings of :func:`find_candidates` (lengths in scene metres)."""

    resolution: int = 192
    """Marching-cubes cells along the bounds' longest axis (6 m room: 3.1 cm) (docs/decisions/discovery-ranking.md)."""
    min_observed: float = 0.5
    """Surface points the scene's views observed less than this are dropped (docs/decisions/discovery-ranking.md)."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """The room's up axis in metres (candidates stand upright on it)."""
    plane_distance: float = 0.02
    """A surface point within this of a support plane belongs to it."""
    support_span: float = 2.0
    """A plane spanning at least this along both in-plane axes is a support; a table top (at most 1.4 m) is not."""
    support_tilt_deg: float = 5.73
    """Degrees within which a support is level (floor, ceiling) or upright (wall); other planes cut through objects."""
    max_supports: int = 12
    """Support planes removed at most (a box room's six, each perhaps seen from both faces)."""
    plane_iterations: int = 400
    """RANSAC draws per plane (seeded: the same planes on every run)."""
    link_distance: float = 0.06
    """Surface points closer than this are in one candidate (twice the meshing cell)."""
    min_points: int = 150
    """Groups with fewer surface points are noise, not candidates."""
    min_size: float = 0.15
    """Groups whose box's largest side is shorter than this are not candidates."""
    max_size: float = 3.0
    """Nor are groups longer than this: what is left of the room, such as wall tops (furniture is at most 1.4 m)."""
    unseen_below: float = 0.5
    """Mean observation of a candidate's column under which it grows to the floor (docs/decisions/discovery-ranking.md)."""
    seed: int = 0
    """Seed of the plane search."""

    def __post_init__(self) -> None:
        for name in ("plane_distance", "support_span", "link_distance", "min_size", "max_size"):
            if not float(getattr(self, name)) > 0:
                raise RegnfError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.resolution < 8:
            raise RegnfError(f"resolution must be >= 8, got {self.resolution}")
        if not 0.0 <= self.min_observed <= 1.0:
            raise RegnfError(f"min_observed must be in [0, 1], got {self.min_observed}")


class Plane(NamedTuple):
    """A plane ``n . x = d`` in metres."""

    normal: np.ndarray
    """(3,) float64 unit normal."""
    offset: float
    """``d``: the signed distance of the origin's projection."""


class Candidate(NamedTuple):
    """One group of surface points that may be an object."""

    box: OrientedBox
    """Upright box around the points, scene metres."""
    points: np.ndarray
    """(n, 3) float64 surface points, scene metres."""


class Candidates(NamedTuple):
    """What :func:`find_candidates` found."""

    candidates: list[Candidate]
    """Largest box first."""
    supports: list[Plane]
    """The support planes removed."""
    surface_points: int
    """Observed surface points before the supports were removed."""


def surface_points(scene_field: Field, config: CandidateConfig) -> np.ndarray:
    """(n, 3) float64 observed surface points of the scene field, metres: the vertices of its
    marching-cubes mesh where its views observed space."""
    mesh = extract_mesh(scene_field, config.resolution, with_color=False)
    v = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32, device=scene_field.device)
    if scene_field.visibility is not None:
        keep = scene_field.visibility.observed(v) >= config.min_observed
        v = v[keep]
    W = scene_field.to_world.detach().cpu().double().numpy()
    p = v.detach().cpu().double().numpy()
    return p @ W[:3, :3].T + W[:3, 3]


def _plane_axes(normal: np.ndarray) -> np.ndarray:
    """(2, 3) two unit axes spanning the plane of ``normal``."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(normal, a)])


def best_plane(points: np.ndarray, config: CandidateConfig, rng: np.random.Generator) -> tuple[Plane, np.ndarray] | None:
    """The level or upright plane (``config.support_tilt_deg``) through most of ``points`` (n, 3)
    by RANSAC, and its inlier mask (n,).

    All draws are scored at once: (iterations, n) distances in chunks, no loop over points.
    """
    n = len(points)
    if n < 3:
        return None
    idx = rng.integers(0, n, size=(config.plane_iterations, 3))
    a, b, c = points[idx[:, 0]], points[idx[:, 1]], points[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    up = np.asarray(config.up, dtype=np.float64) / np.linalg.norm(config.up)
    cos_up = np.abs(normals @ up) / np.maximum(norm, 1e-300)
    tilt = math.radians(config.support_tilt_deg)
    ok = (norm > 1e-9) & ((cos_up >= math.cos(tilt)) | (cos_up <= math.sin(tilt)))
    if not ok.any():
        return None
    normals, a = normals[ok] / norm[ok, None], a[ok]
    offsets = np.einsum("ij,ij->i", normals, a)
    counts = np.zeros(len(normals), dtype=np.int64)
    for start in range(0, n, 20_000):  # chunks of points, all planes at once (memory bound)
        chunk = points[start:start + 20_000]
        counts += (np.abs(chunk @ normals.T - offsets) <= config.plane_distance).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = np.abs(points @ normals[best] - offsets[best]) <= config.plane_distance
    # Refit to the inliers (least squares), then take the inliers of the refined plane.
    q = points[inliers]
    centre = q.mean(axis=0)
    normal = np.linalg.svd(q - centre, full_matrices=False)[2][-1]
    inliers = np.abs((points - centre) @ normal) <= config.plane_distance
    return Plane(normal, float(centre @ normal)), inliers


def remove_supports(points: np.ndarray, config: CandidateConfig) -> tuple[np.ndarray, list[Plane]]:
    """``points`` less the support planes' points, and the planes.

    Planes are taken largest first; the search stops at the first plane that spans less than
    ``support_span`` along either in-plane axis (an object's face, such as a table top), so
    that what stands in the room is never cut by a plane of its own.
    """
    rng = np.random.default_rng(config.seed)
    supports: list[Plane] = []
    remaining = points
    while len(supports) < config.max_supports:
        found = best_plane(remaining, config, rng)
        if found is None:
            break
        plane, inliers = found
        # The support is the largest connected patch of the plane's points: a plane also
        # grazes objects elsewhere (a seat at a table top's height), which must stay.
        at = np.flatnonzero(inliers)
        labels = groups(remaining[at], config.link_distance)
        patch = at[labels == np.argmax(np.bincount(labels))]
        q = remaining[patch] @ _plane_axes(plane.normal).T  # (k, 2) in-plane coordinates
        lo, hi = np.quantile(q, [0.01, 0.99], axis=0)  # a few stray points do not make a wall
        if np.any(hi - lo < config.support_span):
            break
        supports.append(plane)
        keep = np.ones(len(remaining), dtype=bool)
        keep[patch] = False
        remaining = remaining[keep]
    return remaining, supports


def groups(points: np.ndarray, link_distance: float) -> np.ndarray:
    """(n,) int group label of each point: connected components of the graph that links points
    closer than ``link_distance``."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(link_distance, output_type="ndarray")
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def upright_box(points: np.ndarray, up: np.ndarray) -> OrientedBox:
    """The smallest box around ``points`` (n, 3) that stands on ``up``: its horizontal
    rectangle is the minimum-area one around the points' convex hull (the optimum has a side
    on a hull edge; every edge is tried at once), its height their extent along ``up``."""
    up = up / np.linalg.norm(up)
    axes = _plane_axes(up)  # (2, 3) horizontal axes
    flat = points @ axes.T  # (n, 2)
    try:
        hull = flat[ConvexHull(flat).vertices]
    except (QhullError, ValueError):  # collinear or too few points: the axis-aligned box
        hull = flat
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    c, s = np.cos(angles), np.sin(angles)
    rot = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], axis=1)  # (m, 2, 2) rows: box axes
    local = np.einsum("mij,kj->mki", rot, hull)  # (m, k, 2)
    lo, hi = local.min(axis=1), local.max(axis=1)
    best = int(np.argmin(np.prod(hi - lo, axis=1)))
    box_axes_2d = rot[best]  # rows: the box's two horizontal axes in (axes) coordinates
    centre_2d = box_axes_2d.T @ (0.5 * (lo[best] + hi[best]))
    half_2d = 0.5 * (hi[best] - lo[best])
    h = points @ up
    # (axes[0], axes[1], up) is right-handed and the box's axes turn the first two in their
    # plane, so (x, y, up) is a proper rotation.
    R = np.stack([box_axes_2d[0] @ axes, box_axes_2d[1] @ axes, up], axis=1)
    centre = centre_2d @ axes + 0.5 * (h.min() + h.max()) * up
    half = np.array([half_2d[0], half_2d[1], 0.5 * (h.max() - h.min())])
    return OrientedBox(centre, np.maximum(half, 1e-3), R)


def level_supports(supports: list[Plane], up: np.ndarray) -> np.ndarray:
    """(k,) heights along ``up`` of the level supports (floors, ceilings)."""
    return np.array([p.offset / float(p.normal @ up) for p in supports if abs(float(p.normal @ up)) > 0.99])


def grown_to_floor(box: OrientedBox, levels: np.ndarray, scene_field: Field, config: CandidateConfig) -> OrientedBox:
    """``box`` (scene metres, upright) grown down to the highest level support below it (at
    heights ``levels``) if its views observed the column between less than
    ``config.unseen_below``; else ``box``."""
    up = box.rotation[:, 2]
    bottom = float(box.center @ up - box.half_extents[2])
    below = levels[levels <= bottom + config.plane_distance]
    if scene_field.visibility is None or len(below) == 0:
        return box
    floor = float(below.max())
    if bottom - floor < 2.0 * config.link_distance:
        return box
    u = (np.arange(6) + 0.5) / 6 * 2.0 - 1.0
    uz = (np.arange(6) + 0.5) / 6
    gx, gy, gz = np.meshgrid(u, u, uz, indexing="ij")
    horizontal = (np.stack([gx, gy], -1).reshape(-1, 2) * box.half_extents[:2]) @ box.rotation[:, :2].T
    heights = floor + gz.reshape(-1) * (bottom - floor)
    pts = box.center - (box.center @ up) * up + horizontal + heights[:, None] * up  # (216, 3) metres
    W = scene_field.to_world.detach().cpu().double().numpy()
    local = (pts - W[:3, 3]) @ np.linalg.inv(W[:3, :3]).T
    seen = scene_field.visibility.observed(torch.as_tensor(local, dtype=torch.float32, device=scene_field.device))
    if float(seen.mean()) >= config.unseen_below:
        return box
    top = bottom + 2.0 * box.half_extents[2]
    half = box.half_extents.copy()
    half[2] = 0.5 * (top - floor)
    centre = box.center - (box.center @ up) * up + 0.5 * (top + floor) * up
    return OrientedBox(centre, half, box.rotation)


def candidate_of(points: np.ndarray, supports: list[Plane], scene_field: Field, config: CandidateConfig) -> Candidate:
    """The candidate of surface points ``points`` (n, 3, scene metres): their upright box, grown
    to the floor among ``supports`` where the views did not observe below it."""
    up = np.asarray(config.up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    box = grown_to_floor(upright_box(points, up), level_supports(supports, up), scene_field, config)
    return Candidate(box, points)


def find_candidates(scene_field: Field, config: CandidateConfig | None = None) -> Candidates:
    """Object candidates of a scene field, with no boxes given.

    Parameters
    ----------
    scene_field : Field
        A room (``to_world`` to metres; its visibility grid, if it has one, restricts the
        surface to what its views observed).
    config : CandidateConfig

    Returns
    -------
    Candidates
        Boxes in scene metres, largest first; ``OrientedBox.transformed`` with the inverse of
        ``scene_field.to_world`` gives a registration proposal.
    """
    cfg = config or CandidateConfig()
    points = surface_points(scene_field, cfg)
    rest, supports = remove_supports(points, cfg)
    labels = groups(rest, cfg.link_distance)
    found = []
    sizes = np.bincount(labels) if len(labels) else np.zeros(0, dtype=np.int64)
    for label in np.flatnonzero(sizes >= cfg.min_points):  # one iteration per large group
        cand = candidate_of(rest[labels == label], supports, scene_field, cfg)
        if not cfg.min_size <= 2.0 * cand.box.half_extents.max() <= cfg.max_size:
            continue
        found.append(cand)
    found.sort(key=lambda c: -float(np.prod(c.box.half_extents)))
    return Candidates(found, supports, len(points))


def box_iou(a: OrientedBox, b: OrientedBox, samples: int = 48) -> float:
    """Volume intersection over union of two oriented boxes in one frame.

    The intersection is counted on a regular grid of ``samples``^3 cell centres in each box
    (the fraction of one box's cells inside the other, times its volume; averaged both ways),
    accurate to about 1 / ``samples`` of the smaller box.
    """
    u = (np.arange(samples) + 0.5) / samples * 2.0 - 1.0
    grid = np.stack(np.meshgrid(u, u, u, indexing="ij"), axis=-1).reshape(-1, 3)  # (s^3, 3) in [-1, 1]

    def inside_fraction(p: OrientedBox, q: OrientedBox) -> float:
        pts = (grid * p.half_extents) @ p.rotation.T + p.center
        local = (pts - q.center) @ q.rotation
        return float(np.mean(np.all(np.abs(local) <= q.half_extents, axis=1)))

    va, vb = 8.0 * float(np.prod(a.half_extents)), 8.0 * float(np.prod(b.half_extents))
    inter = 0.5 * (inside_fraction(a, b) * va + inside_fraction(b, a) * vb)
    return inter / (va + vb - inter)
