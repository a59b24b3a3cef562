"""Upright starts (a yaw sweep) and the SDF screening of hypotheses, against known placements."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from regnf.registration.initialisation import Hypothesis, InitConfig, initial_hypotheses
from regnf.registration.metrics import geodesic_angle
from regnf.registration.pipeline import RegistrationConfig, sample_pair, sample_tensors
from regnf.registration.refinement import RefineConfig
from regnf.registration.screening import screen_hypotheses
from regnf.registration.transform import SimilarityTransform
from regnf.registration.upright import UprightPrior, axis_rotation, rotation_between, yaw_starts

from .fixtures import make_object, make_scene, object_box, placement
from .test_visibility_weighting import SEEN_BELOW_X, seen_from_minus_x

N_YAWS = 24
YAW = 2 * np.pi * 5 / N_YAWS
TRUE_START = N_YAWS - 5  # scene -> library turns by -YAW: the sweep's start 19
M = placement([0, 0, 1], YAW, [0.3, -0.2, 0.0], 1.3)  # object -> scene


def test_rotation_between_and_axis_rotation_closed_forms() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        R = rotation_between(a, b)
        assert np.allclose(R @ a, b, atol=1e-12)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        # The smallest rotation: its angle is the angle between the vectors.
        assert geodesic_angle(R) == pytest.approx(np.arccos(np.clip(a @ b, -1, 1)), abs=1e-9)
    z = np.array([0.0, 0.0, 1.0])
    assert np.allclose(rotation_between(z, -z) @ z, -z)
    assert np.allclose(axis_rotation(z, np.pi / 2) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@pytest.fixture(scope="module")
def pair() -> dict:
    scene, library = make_scene(M), make_object()
    proposal = object_box().transformed(M)
    sampling = dataclasses.replace(RegistrationConfig().scene_sampling, rays_per_side=40)
    cfg = RegistrationConfig(scene_sampling=sampling, library_sampling=sampling)
    scene_s, lib_s = sample_pair(scene, library, proposal, cfg)
    prior = UprightPrior(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), proposal.center)
    truth = SimilarityTransform.from_matrix(np.linalg.inv(M))
    return {"scene": scene, "library": library, "scene_s": scene_s, "lib_s": lib_s, "prior": prior,
            "truth": truth}


def test_a_start_of_the_sweep_is_the_true_placement(pair: dict) -> None:
    """The whole object seen: the start at the true yaw is the true rotation, and nearly the
    true scale and translation (heights matched, bases level, box centre on the object's
    centre; the scene's sampling drops the points within 1 % of its box's diagonal of the
    floor, so its height is short by that much)."""
    starts = yaw_starts(pair["scene_s"].points, pair["lib_s"].points, pair["prior"], N_YAWS)
    assert len(starts) == N_YAWS
    truth = pair["truth"]
    best = starts[TRUE_START]
    assert geodesic_angle(np.asarray(best.R) @ np.asarray(truth.R).T) < 1e-9
    assert best.s == pytest.approx(truth.s, rel=0.03)
    assert np.linalg.norm(best.t - truth.t) < 0.03
    for k, T in enumerate(starts):  # evenly spaced about the up axis, all upright
        assert np.allclose(np.asarray(T.R) @ [0, 0, 1], [0, 0, 1], atol=1e-12)
        angle = geodesic_angle(np.asarray(T.R) @ np.asarray(truth.R).T)
        step = min(abs(k - TRUE_START), N_YAWS - abs(k - TRUE_START))
        assert angle == pytest.approx(2 * np.pi * step / N_YAWS, abs=1e-9)


def test_half_seen_object_gets_a_start_near_the_truth(pair: dict) -> None:
    """Seen from one side only: ICP from the sweep still lands near the truth."""
    s = pair["scene_s"]
    seen = s.points[:, 0] < SEEN_BELOW_X
    half = type(s)(s.points[seen], s.normals[seen], s.view_ids[seen])
    hyps = initial_hypotheses(half, pair["lib_s"], InitConfig(), upright=pair["prior"], limit=12)
    truth = pair["truth"]
    angles = [geodesic_angle(np.asarray(h.transform.R) @ np.asarray(truth.R).T) for h in hyps]
    assert min(angles) < 0.05


def test_the_same_hypotheses_with_the_sweep_shared_between_threads(pair: dict) -> None:
    """With two workers the sweep's ICP starts are shared by a helper thread and, once RANSAC
    is done, the calling one: the same hypotheses, bit for bit, as on one thread."""
    args = (pair["scene_s"], pair["lib_s"], InitConfig())
    alone = initial_hypotheses(*args, upright=pair["prior"], limit=12, workers=1)
    shared = initial_hypotheses(*args, upright=pair["prior"], limit=12, workers=2)
    assert len(alone) == len(shared) > 1
    for a, b in zip(alone, shared):
        assert np.array_equal(a.transform.matrix(), b.transform.matrix()) and a.fitness == b.fitness


def test_screening_puts_the_true_pose_before_a_half_turn(pair: dict) -> None:
    """Scene seen from -x only: a half turn about the up axis fits the seen half, but puts
    library surface into observed free space; the screening ranks the truth first."""
    scene, library, truth = pair["scene"], pair["library"], pair["truth"]
    A, B = sample_tensors(pair["scene_s"], pair["lib_s"], library.device)
    keep = (A[:, 0] < SEEN_BELOW_X)
    A = A[keep]
    c = np.array([0.0, 0.0, 0.375])
    half_turn = SimilarityTransform(axis_rotation(np.array([0.0, 0.0, 1.0]), np.pi), np.zeros(3), 1.0)
    about_c = SimilarityTransform(np.eye(3), c - half_turn.apply(c[None])[0], 1.0).compose(half_turn)
    flipped = about_c.compose(truth)
    hyps = [Hypothesis(flipped, 0.9, 0.0), Hypothesis(truth, 0.5, 0.0)]  # ICP prefers the flip
    scene.visibility = seen_from_minus_x(np.array([[-1.5, -1.5, -0.2], [1.5, 1.5, 1.2]]))
    try:
        ranked = screen_hypotheses(scene, library, A, B, hyps, RefineConfig(), keep=2)
    finally:
        scene.visibility = None
    assert ranked[0].transform is truth


def test_the_sweep_covers_one_period_of_the_symmetry(pair: dict) -> None:
    """A k-fold object gets the yaws of its first 1/k turn, a round one yaw 0 only: the other
    yaws start poses the symmetry maps onto these."""
    args = (pair["scene_s"].points, pair["lib_s"].points, pair["prior"], N_YAWS)
    full = yaw_starts(*args)
    for period, expected in ((2 * np.pi, N_YAWS), (2 * np.pi / 4, N_YAWS // 4), (np.pi, N_YAWS // 2),
                             (0.0, 1)):
        starts = yaw_starts(*args, period=period)
        assert len(starts) == expected
        for a, b in zip(starts, full):  # the same starts, in order
            assert np.allclose(a.matrix(), b.matrix())


def test_the_sweep_period_follows_the_declared_symmetry_about_the_up_axis() -> None:
    from regnf.registration.initialisation import ObjectSymmetry, _yaw_period

    up = UprightPrior(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), np.zeros(3))
    z, x = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    assert _yaw_period(None, up) == pytest.approx(2 * np.pi)
    assert _yaw_period(ObjectSymmetry(1, z), up) == pytest.approx(2 * np.pi)
    assert _yaw_period(ObjectSymmetry(4, z), up) == pytest.approx(np.pi / 2)
    assert _yaw_period(ObjectSymmetry(4, -z), up) == pytest.approx(np.pi / 2)
    assert _yaw_period(ObjectSymmetry(0, z), up) == 0.0
    # A symmetry about another axis leaves every yaw distinct.
    assert _yaw_period(ObjectSymmetry(2, x), up) == pytest.approx(2 * np.pi)
