"""Signs and distances of meshes as users have them, against the exact SDFs of known shapes.

The defective meshes come from ``benchmarks/defective_meshes.py`` (holes, flipped faces,
duplicates, soups, overlapping parts, Y-up...). Signs are compared with the analytic SDF's at
points more than 1 % of the diagonal from the surface: they must all agree, except near a
hole, where the winding number is about 0.5 and the exact surface is missing (there, under
0.1 % of the points disagree, all within one hole radius of a hole's rim).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from regnf.benchmarks.defective_meshes import (
    DEFECTS,
    HOLE_RADIUS,
    SHAPES,
    Y_UP_FILE,
    defective_mesh,
    unsignable_meshes,
)
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.io.checkpoint import load_field
from regnf.meshes.mesh_repair import UP_AXES, MeshError, repair_mesh, up_rotation
from regnf.meshes.mesh_sign import SignedMesh
from regnf.meshes.winding import (
    RayWinding,
    WindingConfig,
    exact_winding_numbers,
    winding_numbers,
)
from regnf.training.distill import DistillConfig, distillation_targets
from tests.cli.cli_helpers import assert_fails, run_cli

MARGIN = 0.01
"""Signs are checked farther than this fraction of the diagonal from the surface."""

HOLED = ("holes", "combined")
"""Defects with holes: signs may differ from the exact shape's near the holes."""


def unit_frame(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Centre and scale of a frame where the clean mesh spans about [-1, 1]."""
    lo, hi = mesh.bounds
    return 0.5 * (lo + hi), float((hi - lo).max()) * 0.5 * 1.15


def probe_points(dm, n: int = 8000, seed: int = 0) -> np.ndarray:
    """Uniform points in the clean box grown by 10 % and points near the clean surface."""
    rng = np.random.default_rng(seed)
    lo, hi = dm.clean.bounds
    pad = 0.1 * (hi - lo)
    uniform = lo - pad + rng.random((n, 3)) * (hi - lo + 2 * pad)
    pts, _ = trimesh.sample.sample_surface(dm.clean, n, seed=seed + 1)
    return np.concatenate([uniform, pts + rng.normal(0.0, 0.02 * dm.diagonal, pts.shape)])


def signed_mesh(dm) -> tuple[SignedMesh, np.ndarray, float]:
    """The repaired, signed mesh of ``dm`` in a unit frame, and that frame."""
    vertices = dm.mesh.vertices @ up_rotation(dm.up).T
    rep = repair_mesh(vertices, dm.mesh.faces, source=f"{dm.shape}/{dm.defect}")
    centre, scale = unit_frame(dm.clean)
    return SignedMesh((rep.vertices - centre) / scale, rep.faces, rep.piece), centre, scale


def rim_distance(dm, points: np.ndarray) -> np.ndarray:
    """Distance of ``points`` to the nearest open edge of the repaired mesh (inf if none)."""
    rep = repair_mesh(dm.mesh.vertices, dm.mesh.faces)
    edges = np.sort(rep.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    rim = rep.vertices[uniq[count == 1]].mean(axis=1)
    if len(rim) == 0 or len(points) == 0:
        return np.full(len(points), np.inf)
    return np.linalg.norm(points[:, None, :] - rim[None], axis=2).min(axis=1)


# ---------------------------------------------------------------------------- winding numbers


def test_exact_winding_number_closed_forms() -> None:
    box = trimesh.creation.box(extents=(2.0, 1.0, 1.0))
    pts = np.array([[0.0, 0.0, 0.0], [0.9, 0.4, -0.4], [1.1, 0.0, 0.0], [5.0, 5.0, 5.0]])
    np.testing.assert_allclose(exact_winding_numbers(box.vertices, box.faces, pts), [1, 1, 0, 0], atol=1e-12)
    # Reversed winding: -1 inside.
    assert exact_winding_numbers(box.vertices, box.faces[:, ::-1], pts[:1])[0] == pytest.approx(-1.0)
    # An a x b rectangle (two triangles) seen from h below its corner: atan(ab / (h sqrt(a^2 + b^2 + h^2))).
    a, b = 1.0, 0.6
    rect = np.array([[0.0, 0.0, 0.0], [a, 0.0, 0.0], [a, b, 0.0], [0.0, b, 0.0]])
    for h in (0.1, 1.0, 3.0):
        w = exact_winding_numbers(rect, [[0, 1, 2], [0, 2, 3]], [[0.0, 0.0, -h]])[0]
        assert 4 * np.pi * w == pytest.approx(np.arctan(a * b / (h * np.sqrt(a * a + b * b + h * h))), rel=1e-9)
    # A flat sheet never reaches 0.5.
    sheet = unsignable_meshes()["flat sheet"]
    rng = np.random.default_rng(0)
    probe = rng.random((2000, 3)) * [1.0, 1.0, 0.02] - [0.0, 0.0, 0.01]
    assert np.abs(exact_winding_numbers(sheet.vertices, sheet.faces, probe)).max() < 0.5


def test_ray_winding_is_exact_on_closed_meshes_and_estimates_holes() -> None:
    """Three overlapping closed boxes (w = 0 to 3: the third lies in the other two's overlap):
    the rays give the exact sum. A box with holes: the same side of 0.5, within 0.25 (a mean
    of 64 rays where the first 5 disagreed), wherever the exact sum is clearly 0 or 1."""
    for defect in ("components", "holes"):
        dm = defective_mesh("box", defect)
        rep = repair_mesh(dm.mesh.vertices, dm.mesh.faces)
        centre, scale = unit_frame(dm.clean)
        V = (rep.vertices - centre) / scale
        pts = (probe_points(dm, n=300) - centre) / scale
        exact = exact_winding_numbers(V, rep.faces, pts)
        w = SignedMesh(V, rep.faces, rep.piece).winding_numbers(pts)
        if defect == "components":
            np.testing.assert_allclose(w, exact, atol=1e-9)
            assert set(np.round(w)) == {0.0, 1.0, 2.0, 3.0}
        else:
            clear = np.abs(exact - np.round(exact)) < 0.05
            np.testing.assert_array_equal(w[clear] > 0.5, exact[clear] > 0.5)
            np.testing.assert_allclose(w[clear], exact[clear], atol=0.25)


def test_undecided_points_refined_by_rays_or_exactly() -> None:
    """Near the holes of a capsule, points whose first rays disagree get the exact sum (or 59
    more rays); a point all of whose 5 first rays agree keeps their verdict, which for a
    winding number w is wrong with probability (1 - w)^5: under 0.5 % of the points whose
    exact value is clearly (by 0.25) on one side."""
    dm = defective_mesh("capsule", "holes")
    rep = repair_mesh(dm.mesh.vertices, dm.mesh.faces)
    centre, scale = unit_frame(dm.clean)
    V = (rep.vertices - centre) / scale
    pts = (probe_points(dm, n=500) - centre) / scale
    rays = RayWinding(V, rep.faces)
    exact = exact_winding_numbers(V, rep.faces, pts)
    clear = np.abs(exact - 0.5) > 0.25
    for cfg in (WindingConfig(exact_pairs=0), WindingConfig(exact_pairs=10**12)):
        w = winding_numbers(rays, pts, cfg)
        assert ((w > 0.5) != (exact > 0.5))[clear].mean() < 0.005
    first = rays.sample(pts, 5, np.random.default_rng(0))
    undecided = ((first >= 1).any(axis=1)) & ((first <= 0).any(axis=1))
    assert undecided.any()
    refined = winding_numbers(rays, pts, WindingConfig(exact_pairs=10**12))
    np.testing.assert_allclose(refined[undecided], exact[undecided], atol=1e-9)


# ---------------------------------------------------------------------------------- repair


def test_repair_counts_and_keeps_face_order() -> None:
    dm = defective_mesh("box", "degenerate")  # a jittered soup with zero-area faces
    rep = repair_mesh(dm.mesh.vertices, dm.mesh.faces)
    clean = dm.clean
    assert rep.report.pieces == 1 and rep.closed and rep.report.duplicate_faces == 0
    assert len(rep.faces) == len(clean.faces)
    assert rep.report.degenerate_faces == len(dm.mesh.faces) - len(clean.faces)
    assert len(rep.vertices) == len(clean.vertices)  # every jittered copy welded, nothing more
    assert rep.report.merged_vertices >= 3 * len(clean.faces) - len(clean.vertices)
    assert (np.diff(rep.face_index) > 0).all()  # surviving faces keep their input order
    # Each repaired face is its input face (welded within 1e-6 of the diagonal).
    np.testing.assert_allclose(rep.vertices[rep.faces], dm.mesh.triangles[rep.face_index], atol=1e-6)
    repaired = trimesh.Trimesh(rep.vertices, rep.faces, process=False)
    assert repaired.is_winding_consistent and repaired.volume == pytest.approx(clean.volume, rel=1e-6)


@pytest.mark.parametrize("defect", ["flipped", "inside-out", "duplicates"])
def test_repair_orients_outward_and_drops_duplicates(defect: str) -> None:
    dm = defective_mesh("chair", defect)
    rep = repair_mesh(dm.mesh.vertices, dm.mesh.faces)
    repaired = trimesh.Trimesh(rep.vertices, rep.faces, process=False)
    assert repaired.is_watertight and repaired.is_winding_consistent
    assert repaired.volume == pytest.approx(dm.clean.volume, rel=1e-9)
    assert len(rep.faces) == len(dm.clean.faces)
    if defect == "duplicates":
        assert rep.report.duplicate_faces == len(dm.mesh.faces) - len(dm.clean.faces)
    else:
        assert rep.report.reoriented_faces == int((dm.mesh.faces != dm.clean.faces).any(axis=1).sum())


def test_a_void_inside_a_solid_stays_a_void() -> None:
    outer = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    void = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    void.invert()  # inward normals: a cavity
    loose = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    loose.apply_translation((3.0, 0.0, 0.0))
    loose.invert()  # a separate part turned inside out: to be turned back
    mesh = trimesh.util.concatenate([outer, void, loose])
    rep = repair_mesh(mesh.vertices, mesh.faces)
    assert rep.report.pieces == 3 and rep.report.cavities == 1 and rep.report.inverted_pieces == 1
    w = exact_winding_numbers(rep.vertices, rep.faces, [[0.0, 0.0, 0.0], [0.75, 0.0, 0.0], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(w, [0.0, 1.0, 1.0], atol=1e-9)


def test_up_rotation_takes_each_axis_to_plus_z() -> None:
    for up in UP_AXES:
        R = up_rotation(up)
        axis = np.zeros(3)
        axis["xyz".index(up[-1])] = -1.0 if up.startswith("-") else 1.0
        np.testing.assert_array_equal(R @ axis, [0.0, 0.0, 1.0])
        assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(up_rotation("y") @ Y_UP_FILE, np.eye(3))
    with pytest.raises(ValueError, match="up axis"):
        up_rotation("w")


# ------------------------------------------------------------------------- signs and distances


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("defect", [d for d in DEFECTS if d != "dense"])
def test_signs_of_defective_meshes_match_the_exact_shape(shape: str, defect: str) -> None:
    dm = defective_mesh(shape, defect)
    sm, centre, scale = signed_mesh(dm)
    pts = probe_points(dm)
    sd, _ = sm.signed_distance((pts - centre) / scale)
    truth = dm.field.sdf(torch.from_numpy(pts)).numpy()
    far = np.abs(truth) > MARGIN * dm.diagonal
    wrong = far & ((sd < 0) != (truth < 0))
    if defect in HOLED:
        assert wrong.sum() <= 0.001 * far.sum(), f"{wrong.sum()} wrong signs of {far.sum()}"
        assert (rim_distance(dm, pts[wrong]) < HOLE_RADIUS * dm.diagonal).all()
    else:
        assert wrong.sum() == 0, f"{wrong.sum()} wrong signs of {far.sum()}"
    if defect not in (*HOLED, "decimated"):
        # Outside, distances are to the clean surface (for overlapping parts, to the nearest
        # part); inside, to the solid's surface (below).
        out = truth > 0
        q = (pts[out] - centre) / scale
        parts = [dm.clean] if defect != "components" else trimesh.util.concatenate(dm.mesh).split(only_watertight=False)
        want = np.min([SignedMesh((p.vertices - centre) / scale, p.faces, np.zeros(len(p.faces), dtype=np.int64))
                       .unsigned_distance(q) for p in parts], axis=0)
        np.testing.assert_allclose(sd[out], want, atol=2e-6)


@pytest.mark.parametrize("shape", ["box", "capsule"])
def test_overlapping_parts_lose_their_internal_faces(shape: str) -> None:
    """Inside a union of overlapping parts the distance is to the union's surface, not to a
    part's face inside another (the box's and capsule's SDFs are exact inside too)."""
    dm = defective_mesh(shape, "components")
    sm, centre, scale = signed_mesh(dm)
    assert sm.surface.internal_faces > 0 and sm.surface.split_faces > 0
    pts = probe_points(dm)
    sd, _ = sm.signed_distance((pts - centre) / scale)
    truth = dm.field.sdf(torch.from_numpy(pts)).numpy()
    inside = truth < -MARGIN * dm.diagonal
    err = np.abs(sd[inside] * scale - truth[inside]) / dm.diagonal
    # Pieces of faces up to split_edge (1 %) long may stay at a part's boundary.
    assert np.percentile(err, 99) < 0.002 and err.max() < sm.config.split_edge


# ------------------------------------------------------------------------------- distillation


@pytest.mark.parametrize("name", sorted(unsignable_meshes()))
def test_unsignable_meshes_are_refused_naming_the_file(name: str) -> None:
    mesh = unsignable_meshes()[name]
    with pytest.raises(MeshError, match=r"^lib/thing\.ply: the mesh (has no|encloses no)") as err:
        distillation_targets(mesh, DistillConfig(pool_surface=2000), source="lib/thing.ply")
    assert "\n" not in str(err.value) and isinstance(err.value, ValueError)


def test_open_box_that_lost_a_whole_side_is_still_a_box() -> None:
    """A quarter of the faces gone (one side of a 12-face box and a half): still signable."""
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.4))
    tray = trimesh.Trimesh(box.vertices, box.faces[3:], process=False)
    targets = distillation_targets(tray, DistillConfig(pool_surface=4000))
    assert (targets.sdf < 0).any() and (targets.sdf > 0).any()


TINY = NeuralSDFConfig(levels=3, features_per_level=2, base_resolution=8, finest_resolution=16,
                       hidden_dim=16, color_hidden_dim=16)


def test_up_y_obj_gives_the_targets_and_field_of_the_z_up_copy(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dm = defective_mesh("chair", "y-up")
    z_path, y_path = tmp_path / "chair.obj", tmp_path / "chair_yup.obj"
    dm.clean.export(z_path)
    dm.mesh.export(y_path)
    z_mesh = trimesh.load(z_path, force="mesh")
    y_mesh = trimesh.load(y_path, force="mesh")
    assert np.abs(y_mesh.bounds[:, 1] - z_mesh.bounds[:, 2]).max() < 1e-9  # the file is Y-up
    cfg = DistillConfig(pool_surface=5000)
    z_targets = distillation_targets(z_mesh, cfg)
    y_targets = distillation_targets(y_mesh, DistillConfig(pool_surface=5000, up="y"))
    for name in ("to_world", "bounds", "points", "sdf", "surface_points", "surface_normals"):
        np.testing.assert_array_equal(getattr(y_targets, name), getattr(z_targets, name), err_msg=name)
    # The same field, through the command line (2 steps of the library preset).
    cache = tmp_path / "cache"
    outs = []
    for path, extra in ((z_path, []), (y_path, ["--up", "y"])):
        out = tmp_path / f"{path.stem}.safetensors"
        status, err = run_cli(capsys, ["distill", "--mesh", str(path), *extra, "--distillation.steps", "2",
                                       "--cache-dir", str(cache), "--out", str(out)])
        assert status == 0, err
        outs.append(load_field(out))
    a, b = (f.state_dict() for f in outs)
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    np.testing.assert_array_equal(outs[0].to_world.numpy(), outs[1].to_world.numpy())


def test_cli_refuses_an_unsignable_mesh_on_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sheet = tmp_path / "sheet.obj"
    unsignable_meshes()["flat sheet"].export(sheet)
    line = assert_fails(capsys, ["distill", "--mesh", str(sheet), "--distillation.steps", "1", "--cache-dir", str(tmp_path / "c")],
                        r"^regnf distill: .*sheet\.obj: the mesh encloses no volume")
    assert str(sheet) in line
    assert not list((tmp_path / "c").glob("fields/*"))  # nothing made
