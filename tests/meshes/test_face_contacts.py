"""Faces split only where parts touch: pairs against brute force, contacts against exact
intersections, and the solid's surface of overlapping boxes against the union's exact SDF."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from regnf.meshes import mesh_sign
from regnf.meshes.face_contacts import box_pairs, split_at_contacts, touching, unit_normals
from regnf.meshes.mesh_repair import MeshError, repair_mesh
from regnf.meshes.mesh_sign import MeshSignConfig, SignedMesh

MARGIN = 0.01
"""Signs are compared farther than this fraction of the diagonal from the surface."""


def test_box_pairs_are_the_boxes_that_meet() -> None:
    rng = np.random.default_rng(0)
    # Mostly small boxes and a few large ones, as the faces of a mesh are.
    size = np.where(rng.random((300, 1)) < 0.05, 0.5, 0.03) * rng.random((300, 3))
    lo = rng.random((300, 3))
    hi = lo + size
    a, b = box_pairs(lo, hi, max_pairs=10**7)
    meet = ((lo[:, None] <= hi[None]) & (hi[:, None] >= lo[None])).all(axis=2)
    want = {(i, j) for i, j in zip(*np.nonzero(np.triu(meet, 1)), strict=True)}
    assert set(zip(a.tolist(), b.tolist(), strict=True)) == want and len(a) == len(want)
    assert box_pairs(lo, hi, max_pairs=10) is None  # more candidates than allowed


def segment_hits_triangle(p: np.ndarray, q: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(n,) whether segments p-q (n, 3) cross triangles (n, 3, 3) (Moller-Trumbore)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = q - p
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-12
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p - tri[:, 0]
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def test_touching_never_misses_an_intersection() -> None:
    """Two triangles in general position intersect exactly when an edge of one crosses the other."""
    rng = np.random.default_rng(1)
    a = rng.random((20000, 3, 3))
    b = rng.random((20000, 3, 3))
    crosses = np.zeros(len(a), dtype=bool)
    for x, y in ((a, b), (b, a)):
        for j in range(3):
            crosses |= segment_hits_triangle(x[:, j], x[:, (j + 1) % 3], y)
    hit = touching(a, unit_normals(a), b, unit_normals(b), pad=1e-9)
    assert crosses.sum() > 1000
    assert hit[crosses].all()
    # Conservative but not blind: most pairs whose boxes meet and that do not cross are told apart.
    assert (~hit[~crosses]).mean() > 0.5


def union_of_boxes(n: int, seed: int) -> tuple[trimesh.Trimesh, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """``n`` overlapping boxes (every other one turned about Z) as one mesh, and each box's
    (half extents, rotation, centre)."""
    rng = np.random.default_rng(seed)
    parts, boxes = [], []
    for i in range(n):
        ext = rng.uniform(0.1, 0.6, 3)
        centre = rng.uniform(-0.25, 0.25, 3)
        rot = Rotation.from_euler("z", rng.uniform(10, 80), degrees=True).as_matrix() if i % 2 else np.eye(3)
        m = trimesh.creation.box(extents=ext)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rot, centre
        m.apply_transform(T)
        parts.append(m)
        boxes.append((ext / 2, rot, centre))
    return trimesh.util.concatenate(parts), boxes


def union_sdf(p: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """Exact outside (and on the surface): the minimum of the boxes' exact SDFs."""
    out = []
    for half, rot, centre in boxes:
        q = np.abs((p - centre) @ rot) - half
        out.append(np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0))
    return np.min(out, axis=0)


def union_surface_points(mesh: trimesh.Trimesh, boxes, n: int) -> np.ndarray:
    """Points of the boxes' surfaces that are not inside another box: the union's surface."""
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=3)
    return pts[union_sdf(pts, boxes) > -1e-9]


@pytest.fixture(scope="module")
def boxes6() -> tuple[trimesh.Trimesh, list, SignedMesh, SignedMesh]:
    mesh, boxes = union_of_boxes(6, seed=2)
    rep = repair_mesh(mesh.vertices, mesh.faces)
    assert rep.report.pieces == 6
    contact = SignedMesh(rep.vertices, rep.faces, rep.piece, MeshSignConfig(box_pairs=0))
    near_boxes = SignedMesh(rep.vertices, rep.faces, rep.piece)
    return mesh, boxes, contact, near_boxes


def test_splitting_at_contacts_leaves_the_union_surface(boxes6) -> None:
    """Every kept face lies on the union's surface (but slivers under ``split_edge`` at the
    curves where boxes cut each other), and every point of the union's surface is on a kept face."""
    mesh, boxes, sm, _ = boxes6
    diag = float(np.linalg.norm(mesh.extents))
    surf = trimesh.Trimesh(sm.surface.vertices, sm.surface.faces, process=False)
    kept, _ = trimesh.sample.sample_surface(surf, 20000, seed=4)
    depth = -union_sdf(kept, boxes)
    assert np.percentile(depth, 99) < 1e-9 and depth.max() < sm.config.split_edge * diag
    gap = sm.unsigned_distance(union_surface_points(mesh, boxes, 20000))
    assert np.percentile(gap, 99) < 1e-6 * diag and gap.max() < sm.config.split_edge * diag


def test_splitting_at_contacts_matches_splitting_near_boxes(boxes6) -> None:
    """Both ways give the union's distances and signs; contacts test fewer pieces of faces."""
    mesh, boxes, contact, near_boxes = boxes6
    diag = float(np.linalg.norm(mesh.extents))
    rng = np.random.default_rng(5)
    lo, hi = mesh.bounds
    pts = lo - 0.1 * diag + rng.random((20000, 3)) * (hi - lo + 0.2 * diag)
    truth = union_sdf(pts, boxes)
    for sm in (contact, near_boxes):
        sd, _ = sm.signed_distance(pts)
        far = np.abs(truth) > MARGIN * diag
        np.testing.assert_array_equal(sd[far] < 0, truth[far] < 0)
        outside = truth > MARGIN * diag
        np.testing.assert_allclose(sd[outside], truth[outside], atol=1e-5 * diag)
    tested = [sm.surface.internal_faces + len(sm.surface.faces) for sm in (contact, near_boxes)]
    assert tested[0] < tested[1] / 2


def test_twenty_overlapping_boxes_take_the_contact_path_and_stay_exact(monkeypatch) -> None:
    """The CAD case: splitting near boxes would pass its budget, so faces are split at contacts."""
    mesh, boxes = union_of_boxes(20, seed=1)
    rep = repair_mesh(mesh.vertices, mesh.faces)
    calls = []

    def spy(*args, **kwargs):
        calls.append(1)
        return split_at_contacts(*args, **kwargs)

    monkeypatch.setattr(mesh_sign, "split_at_contacts", spy)
    sm = SignedMesh(rep.vertices, rep.faces, rep.piece)
    assert calls == [1]
    diag = float(np.linalg.norm(mesh.extents))
    # Many curves where boxes cut each other: a few more points lie within a sliver of one.
    gap = sm.unsigned_distance(union_surface_points(mesh, boxes, 20000))
    assert (gap > 1e-6 * diag).mean() < 0.02 and gap.max() < sm.config.split_edge * diag
    surf = trimesh.Trimesh(sm.surface.vertices, sm.surface.faces, process=False)
    kept, _ = trimesh.sample.sample_surface(surf, 20000, seed=4)
    depth = -union_sdf(kept, boxes)
    assert (depth > 1e-9).mean() < 0.02 and depth.max() < sm.config.split_edge * diag


def test_too_many_pieces_of_faces_are_refused_naming_the_file(boxes6) -> None:
    mesh, _, _, _ = boxes6
    rep = repair_mesh(mesh.vertices, mesh.faces)
    with pytest.raises(MeshError, match=r"^cad/boxes\.ply: \d+ of its \d+ faces reach into other parts, .*"
                                        r"more than 4000000 face pairs or 100 pieces of faces"):
        SignedMesh(rep.vertices, rep.faces, rep.piece, MeshSignConfig(box_pairs=0, contact_pieces=100),
                   source="cad/boxes.ply")


def test_a_soup_of_random_triangles_is_refused_before_the_costly_steps() -> None:
    rng = np.random.default_rng(0)
    v = rng.random((450, 3))
    rep = repair_mesh(v, np.arange(450).reshape(-1, 3))
    with pytest.raises(MeshError, match=r"^soup\.ply: its faces bound no solid: rays from \d+ % of the points"):
        SignedMesh(rep.vertices, rep.faces, rep.piece, source="soup.ply")
