"""Registration errors against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from regnf.fields.field import Symmetry
from regnf.fields.similarity import similarity_matrix
from regnf.registration.metrics import (
    RegistrationErrors,
    euler_rmse,
    geodesic_angle,
    registration_errors,
    symmetry_rotations,
    wrap_angle,
)
from regnf.registration.transform import SimilarityTransform

from .fixtures import rot

RNG = np.random.default_rng(7)
POINTS = RNG.uniform(-0.5, 0.5, (400, 3))  # "surface" points, library frame
POINTS[:2] = [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]  # AABB centre exactly at the origin
EYE4 = np.eye(4)
IDENT = SimilarityTransform.identity()


def errors(
    T: SimilarityTransform, T_gt: SimilarityTransform = IDENT, order: int = 1, **kw: object
) -> RegistrationErrors:
    args: dict = {
        "scene_world_scale": 1.0,
        "library_points": POINTS,
        "library_diagonal_m": 1.0,
        "library_to_world": EYE4,
        "symmetry": Symmetry(order),
    }
    args.update(kw)
    return registration_errors(T, T_gt, **args)


def rz(angle: float) -> SimilarityTransform:
    return SimilarityTransform(rot([0, 0, 1], angle), np.zeros(3), 1.0)


def test_identity_is_zero_everywhere() -> None:
    T = SimilarityTransform(rot([1, 2, 3], 0.7), np.array([0.1, -0.2, 0.3]), 1.7)
    e = errors(T, T, order=0)
    assert max(abs(v) for v in e) < 1e-9


def test_small_yaw_and_symmetry_orders() -> None:
    for order, expect_sym in ((1, 0.1), (0, 0.0), (4, 0.1)):
        e = errors(rz(0.1), order=order)
        assert e.rot_geodesic_rad == pytest.approx(0.1, abs=1e-12)
        assert e.rot_geodesic_sym_rad == pytest.approx(expect_sym, abs=1e-7)
        assert e.rot_euler_rmse_rad == pytest.approx(0.1 / math.sqrt(3), abs=1e-12)
        assert e.rot_euler_rmse_sym_rad == pytest.approx(expect_sym / math.sqrt(3), abs=1e-7)
        # A rotation about the axis through the object's centre (the origin) moves no centre.
        assert e.trans_m == pytest.approx(0.0, abs=1e-12)
        assert e.add_rel > 0.01
        assert e.add_rel_sym == pytest.approx(0.0 if order == 0 else e.add_rel, abs=1e-7)


def test_quarter_turn_with_fourfold_symmetry() -> None:
    e = errors(rz(math.pi / 2), order=4)
    assert e.rot_geodesic_rad == pytest.approx(math.pi / 2)
    assert e.rot_geodesic_sym_rad == pytest.approx(0.0, abs=1e-7)
    assert e.add_rel_sym == pytest.approx(0.0, abs=1e-12)
    e2 = errors(rz(math.pi / 2), order=2)
    assert e2.rot_geodesic_sym_rad == pytest.approx(math.pi / 2)


def test_translation_exact_numbers() -> None:
    T = SimilarityTransform(np.eye(3), np.array([0.3, 0.0, 0.4]), 1.0)
    e = errors(T, scene_world_scale=2.0, library_diagonal_m=4.0)
    assert e.trans_rmse_norm == pytest.approx(0.5 / math.sqrt(3))
    assert e.trans_m == pytest.approx(1.0)  # 0.5 scene units * 2 m per unit
    assert e.trans_rel_diag == pytest.approx(0.25)
    assert e.add_m == pytest.approx(1.0)
    assert e.add_rel == pytest.approx(0.25)
    assert e.rot_geodesic_rad == 0.0 and e.scale_abs == 0.0
    # A yaw symmetry turns the object about its own centre: it cannot undo a translation.
    e0 = errors(T, order=0, scene_world_scale=2.0, library_diagonal_m=4.0)
    assert e0.trans_m_sym == pytest.approx(1.0, abs=1e-9)
    assert 0.9 < e0.add_m_sym <= e0.add_m + 1e-12  # a turn cannot remove the shift


def test_scale_exact_numbers() -> None:
    T_gt = SimilarityTransform(np.eye(3), np.zeros(3), 2.0)
    T = SimilarityTransform(np.eye(3), np.zeros(3), 2.5)
    e = errors(T, T_gt)
    assert e.scale_abs == pytest.approx(0.5)
    assert e.scale_rel == pytest.approx(0.25)
    # T^-1 p = p / 2.5, T_gt^-1 p = p / 2: ADD = mean |p| * (1/2 - 1/2.5) = 0.1 mean |p|.
    assert e.add_m == pytest.approx(0.1 * np.linalg.norm(POINTS, axis=1).mean())
    assert e.trans_m == pytest.approx(0.0, abs=1e-12)  # the centre is the origin


def test_euler_wrapping() -> None:
    e = errors(rz(math.pi - 0.05), rz(-math.pi + 0.05))
    assert e.rot_euler_rmse_rad == pytest.approx(0.1 / math.sqrt(3), abs=1e-9)
    assert e.rot_geodesic_rad == pytest.approx(0.1, abs=1e-9)
    np.testing.assert_allclose(
        wrap_angle(np.array([3 * math.pi / 2, -3 * math.pi / 2])), [-math.pi / 2, math.pi / 2]
    )
    assert float(euler_rmse(rot([1, 0, 0], 0.3), np.eye(3))) == pytest.approx(0.3 / math.sqrt(3))


def test_geodesic_precise_at_small_and_large_angles() -> None:
    for a in (1e-8, 1e-4, 1.0, math.pi - 1e-6):
        assert float(geodesic_angle(rot([0.3, -1, 2], a))) == pytest.approx(a, rel=1e-6)


def test_symmetry_axis_follows_library_to_world() -> None:
    # Library field -> canonical: x -> 2 x + (0.4, -0.2, 0); the canonical z axis runs
    # through (-0.2, 0.1, *) in the field frame.
    W = similarity_matrix(np.eye(3), np.array([0.4, -0.2, 0.0]), 2.0)
    a = np.array([-0.2, 0.1, 0.0])
    R, t = symmetry_rotations(np.array([0.7]), W)
    np.testing.assert_allclose(R[0], rot([0, 0, 1], 0.7), atol=1e-12)
    np.testing.assert_allclose(R[0] @ a + t[0], a, atol=1e-12)  # the axis is fixed
    # An estimate off by a turn about that axis: wrong without symmetry, exact with it.
    T_gt = SimilarityTransform(rot([1, 1, 0], 0.4), np.array([0.1, 0.2, -0.3]), 0.8)
    for order, angle in ((0, 0.7), (9, 2 * math.pi / 9)):
        Rs, ts = symmetry_rotations(np.array([angle]), W)
        T = SimilarityTransform(Rs[0], ts[0], 1.0).compose(T_gt)
        e = errors(T, T_gt, order=order, library_to_world=W)
        assert e.rot_geodesic_rad == pytest.approx(angle, abs=1e-9)
        assert e.trans_m > 0.01 and e.add_rel > 0.01
        for v in (e.rot_geodesic_sym_rad, e.trans_m_sym, e.add_rel_sym, e.trans_rmse_norm_sym):
            assert v == pytest.approx(0.0, abs=1e-6)


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="library_points"):
        errors(IDENT, library_points=np.zeros((0, 3)))
    with pytest.raises(ValueError, match="scene_world_scale"):
        errors(IDENT, scene_world_scale=0.0)
    with pytest.raises(ValueError, match="order"):
        errors(IDENT, symmetry=Symmetry(-1))
