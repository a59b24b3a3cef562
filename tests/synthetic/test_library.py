"""Library objects: watertight, canonical frame, coloured, deterministic, symmetric as declared."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from regnf.synthetic.library import LIBRARY_NAMES, library_object_names, make_library_object

SYMMETRIC = {"et": 4, "t": 2, "wt": 0}


@pytest.mark.parametrize("name", LIBRARY_NAMES)
def test_object_is_one_watertight_canonical_coloured_mesh(name: str) -> None:
    obj = make_library_object(name)
    mesh = obj.mesh
    assert obj.name == name
    assert mesh.is_watertight and mesh.is_volume
    assert mesh.body_count == 1
    assert mesh.volume > 0.005
    lo, hi = mesh.bounds
    assert abs(lo[2]) < 1e-6
    np.testing.assert_allclose(0.5 * (lo[:2] + hi[:2]), 0.0, atol=1e-6)
    # Realistic furniture sizes (metres).
    assert 0.5 < hi[2] < 1.1
    assert 0.4 <= hi[0] - lo[0] <= 1.5 and 0.4 <= hi[1] - lo[1] <= 1.1
    assert mesh.visual.kind == "face"
    colors = np.asarray(mesh.visual.face_colors)
    assert colors.shape == (len(mesh.faces), 4)
    assert len(np.unique(colors[:, :3], axis=0)) >= 2
    assert np.all(colors[:, 3] == 255)


@pytest.mark.parametrize("name", ["dc", "fc", "wt"])
def test_object_is_deterministic(name: str) -> None:
    a, b = make_library_object(name).mesh, make_library_object(name).mesh
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.visual.face_colors, b.visual.face_colors)
    # Callers get copies: mutating one must not leak into the next call.
    a.apply_translation([1.0, 0.0, 0.0])
    assert make_library_object(name).mesh.bounds[0, 2] == 0.0
    assert abs(make_library_object(name).mesh.bounds.mean(axis=0)[0]) < 1e-6


def test_labels_and_symmetry_orders() -> None:
    assert library_object_names("chair") == ("c", "dc", "fc", "fc-nop", "mc")
    assert library_object_names("table") == ("et", "t", "wt")
    assert library_object_names() == LIBRARY_NAMES
    for name in LIBRARY_NAMES:
        obj = make_library_object(name)
        assert obj.symmetry_order == SYMMETRIC.get(name, 1)
    with pytest.raises(KeyError, match="unknown library object"):
        make_library_object("sofa")


def test_pillow_is_the_only_difference_between_fc_and_fc_nop() -> None:
    fc, nop = make_library_object("fc").mesh, make_library_object("fc-nop").mesh
    np.testing.assert_allclose(fc.bounds, nop.bounds, atol=1e-9)
    assert fc.volume > nop.volume + 0.005  # the pillow (about 0.02 m^3)
    assert (
        len(np.unique(fc.visual.face_colors, axis=0))
        == len(np.unique(nop.visual.face_colors, axis=0)) + 1
    )


def _relative_symmetric_difference(mesh: trimesh.Trimesh, angle: float) -> float:
    """vol(A xor R A) / vol(A) for a rotation R by ``angle`` about +Z (exact booleans)."""
    rotated = mesh.copy()
    rotated.apply_transform(trimesh.transformations.rotation_matrix(angle, [0, 0, 1]))
    union = trimesh.boolean.union([mesh, rotated], engine="manifold")
    inter = trimesh.boolean.intersection([mesh, rotated], engine="manifold")
    return (union.volume - inter.volume) / mesh.volume


@pytest.mark.parametrize(
    "name, angles",
    [("et", [np.pi / 2, np.pi, 3 * np.pi / 2]), ("t", [np.pi]), ("wt", [0.3, 1.234, 2.9, 4.0])],
)
def test_tables_have_their_declared_symmetry(name: str, angles: list[float]) -> None:
    mesh = make_library_object(name).mesh
    for a in angles:
        assert _relative_symmetric_difference(mesh, a) < 5e-3, (name, a)


@pytest.mark.parametrize("name, angle", [("et", np.pi / 4), ("t", np.pi / 2)])
def test_tables_lack_other_symmetries(name: str, angle: float) -> None:
    assert _relative_symmetric_difference(make_library_object(name).mesh, angle) > 0.1


@pytest.mark.parametrize("name", library_object_names("chair"))
def test_chairs_are_not_symmetric(name: str) -> None:
    mesh = make_library_object(name).mesh
    for a in (np.pi / 2, np.pi):
        assert _relative_symmetric_difference(mesh, a) > 0.1, (name, a)


def test_chair_backs_face_minus_x() -> None:
    """A seated person faces +X, so the tall back of every chair is on the -X side."""
    for name in library_object_names("chair"):
        v = make_library_object(name).mesh.vertices
        top = v[v[:, 2] > v[:, 2].max() - 0.05]
        assert top[:, 0].mean() < -0.1, name
