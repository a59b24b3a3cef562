"""FPFH + RANSAC + ICP initialisation against known similarity placements."""

from __future__ import annotations

import numpy as np
import pytest

from regnf.registration.initialisation import (
    Hypothesis,
    InitConfig,
    fgr_baseline,
    initial_hypotheses,
)
from regnf.registration.metrics import geodesic_angle
from regnf.registration.sampling import SamplingConfig, SurfaceSamples, sample_surface
from regnf.registration.transform import SimilarityTransform

from .fixtures import OBJECT_HI, OBJECT_LO, make_object, make_scene, object_box, placement

DIAG = float(np.linalg.norm(OBJECT_HI - OBJECT_LO))
CENTRE = 0.5 * (OBJECT_LO + OBJECT_HI)

CASES = {
    # name: (axis, angle, translation, scale, on a floor)
    "yaw_on_floor_s2.5": ([0, 0, 1], 2.5, [0.6, -0.4, 0.0], 2.5, True),
    "tumbled_180deg_s0.5": ([1, 2, 0.5], np.pi, [0.2, 0.1, -0.4], 0.5, False),
}


@pytest.fixture(scope="module")
def library() -> SurfaceSamples:
    return sample_surface(make_object(), None, SamplingConfig(), side="library")


def scene_samples(name: str) -> tuple[SurfaceSamples, SimilarityTransform]:
    axis, angle, t, s, floor = CASES[name]
    M = placement(axis, angle, t, s)  # object (= library field) -> scene
    scene = make_scene(M, floor=floor)
    # A tumbled object in the air, every side of it exact (an analytic field): no floor to
    # remove, and no underside left unobserved by cameras above it to drop.
    cfg = SamplingConfig(remove_floor=floor, underside_deg=60.0 if floor else 0.0)
    samples = sample_surface(scene, object_box().transformed(M), cfg, side="scene")
    return samples, SimilarityTransform.from_matrix(M).inverse()


@pytest.fixture(scope="module")
def results(library: SurfaceSamples) -> dict[str, tuple[list[Hypothesis], SimilarityTransform]]:
    out = {}
    for name in CASES:
        scene, T_gt = scene_samples(name)
        out[name] = (initial_hypotheses(scene, library, InitConfig()), T_gt)
    return out


@pytest.mark.parametrize("name", list(CASES))
def test_best_hypothesis_recovers_the_placement(results, name: str) -> None:
    hyps, T_gt = results[name]
    T = hyps[0].transform
    rot_err = float(geodesic_angle(T_gt.R.T @ T.R))
    # Where the estimate puts the object's centre in the scene, relative to its diagonal there.
    centre_err = np.linalg.norm(
        T.inverse().apply(CENTRE[None]) - T_gt.inverse().apply(CENTRE[None])
    )
    rel_trans = centre_err / (DIAG / T_gt.s)
    assert rot_err < 0.05, f"rotation off by {rot_err:.3f} rad"
    assert rel_trans < 0.03, f"centre off by {rel_trans:.3%} of the diagonal"
    assert abs(T.s / T_gt.s - 1) < 0.03, f"scale {T.s:.4f} vs {T_gt.s:.4f}"
    # The scene cameras of a tumbled object see its bottom, which no library camera sees.
    assert hyps[0].fitness > (0.9 if CASES[name][4] else 0.6)
    assert 0 <= hyps[0].inlier_rmse < 0.01 * DIAG  # library units


def test_hypotheses_are_distinct_and_ranked(results, library: SurfaceSamples) -> None:
    cfg = InitConfig()
    lo, hi = library.points.min(0), library.points.max(0)
    centre, size = 0.5 * (lo + hi), float((hi - lo).max())
    for hyps, _ in results.values():
        assert 1 <= len(hyps) <= cfg.top_k
        fits = [h.fitness for h in hyps]
        assert fits == sorted(fits, reverse=True)
        for i in range(len(hyps)):
            for j in range(i):  # another turn, another size or another place
                a, b = hyps[i].transform, hyps[j].transform
                turn = np.degrees(geodesic_angle(a.R.T @ b.R)) >= cfg.min_rotation_deg
                size_ = abs(np.log(a.s / b.s)) >= np.log1p(cfg.min_scale_change)
                shift = np.linalg.norm(a.inverse().apply(centre[None]) - b.inverse().apply(centre[None])) * a.s
                assert turn or size_ or shift >= cfg.min_shift * size


def test_top_k_one_and_more_runs(library: SurfaceSamples) -> None:
    scene, _ = scene_samples("tumbled_180deg_s0.5")
    one = initial_hypotheses(scene, library, InitConfig(top_k=1))
    assert len(one) == 1
    many = initial_hypotheses(scene, library, InitConfig(top_k=6, ransac_runs=6))
    assert 1 <= len(many) <= 6


def test_deterministic_for_a_seed(library: SurfaceSamples, results) -> None:
    scene, _ = scene_samples("tumbled_180deg_s0.5")
    again = initial_hypotheses(scene, library, InitConfig())
    first = results["tumbled_180deg_s0.5"][0]
    assert len(again) == len(first)
    for a, b in zip(again, first):
        np.testing.assert_allclose(a.transform.matrix(), b.transform.matrix(), atol=1e-9)


def test_fgr_baseline_runs(library: SurfaceSamples) -> None:
    scene, T_gt = scene_samples("yaw_on_floor_s2.5")
    h = fgr_baseline(scene, library, InitConfig())
    assert isinstance(h, Hypothesis)
    assert np.isfinite(h.transform.matrix()).all()
    assert 0.0 <= h.fitness <= 1.0
    # FGR estimates no scale: the scale is the radius-ratio pre-estimate, near the truth.
    assert abs(h.transform.s / T_gt.s - 1) < 0.15


def test_bad_inputs_raise(library: SurfaceSamples) -> None:
    tiny = SurfaceSamples(library.points[:5], library.normals[:5], library.view_ids[:5])
    with pytest.raises(ValueError, match="too few"):
        initial_hypotheses(tiny, library)
    with pytest.raises(ValueError, match="confidence"):
        InitConfig(ransac_confidence=500)
    bad = SurfaceSamples(library.points[:, :2], library.normals, library.view_ids)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        initial_hypotheses(bad, library)


# -- hypotheses equal under the object's symmetry are one ------------------------------------
def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(angle * a / np.linalg.norm(a)).as_matrix()


def test_symmetric_angle_is_zero_on_the_group_and_the_tilt_off_it() -> None:
    from regnf.registration.metrics import symmetric_angle

    axis = np.array([0.3, -0.2, 0.9])
    axis /= np.linalg.norm(axis)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    for k in range(4):
        assert symmetric_angle(_rot(axis, k * np.pi / 2), axis, 4) == pytest.approx(0.0, abs=1e-7)
    assert symmetric_angle(_rot(axis, np.pi / 4), axis, 4) == pytest.approx(np.pi / 4)
    assert symmetric_angle(_rot(axis, 1.234), axis, 0) == pytest.approx(0.0, abs=1e-7)
    # A tilt of 0.3 rad about an axis perpendicular to the symmetry axis, after any spin about
    # it, is 0.3 rad from the group (the nearest symmetry undoes the spin).
    Q = _rot(side, 0.3) @ _rot(axis, 2.0)
    assert symmetric_angle(Q, axis, 0) == pytest.approx(0.3, abs=1e-7)
    assert symmetric_angle(Q, axis, 1) == pytest.approx(geodesic_angle(Q))


def test_hypotheses_a_symmetry_maps_onto_each_other_are_merged() -> None:
    from regnf.registration.initialisation import ObjectSymmetry, _select

    axis = np.array([0.0, 0.0, 1.0])
    R1 = _rot([1.0, 0.5, 0.2], 0.7)
    spun = [_rot(axis, a) @ R1 for a in (0.0, 0.45, 0.9, 1.3)]  # equal poses of a round table
    tilted = _rot([1.0, 0.0, 0.0], 0.6) @ R1  # a different pose
    hyps = [Hypothesis(SimilarityTransform(R, np.zeros(3), 1.0), f, 0.01)
            for R, f in zip([*spun, tilted], (0.9, 0.85, 0.8, 0.75, 0.7))]
    cfg = InitConfig(top_k=5)
    assert len(_select(hyps, cfg)) == 5  # no symmetry: five distinct rotations
    kept = _select(hyps, cfg, ObjectSymmetry(0, axis))
    assert [h.fitness for h in kept] == [0.9, 0.7]  # the best of the four, and the tilted one
    four_fold = _select(hyps, cfg, ObjectSymmetry(4, axis))
    assert len(four_fold) == 5  # spins of 0.45, 0.9, 1.3 rad are at least 15 degrees from quarter turns
    quarter = [Hypothesis(SimilarityTransform(_rot(axis, k * np.pi / 2) @ R1, np.zeros(3), 1.0), 0.9 - k / 10, 0.01)
               for k in range(4)]
    assert len(_select(quarter, cfg, ObjectSymmetry(4, axis))) == 1


def test_hypotheses_of_one_turn_at_another_size_or_place_are_kept_apart() -> None:
    from regnf.registration.initialisation import ObjectSymmetry, _select

    axis = np.array([0.0, 0.0, 1.0])
    R = _rot([1.0, 0.5, 0.2], 0.7)
    centre, size = np.array([0.0, 0.0, 0.5]), 2.0

    def hyp(angle: float, s: float, shift: float, fit: float) -> Hypothesis:
        # Spun about the library's axis, at scale s, the library centre moved by shift (library units).
        Q = _rot(axis, angle) @ R
        t = centre - s * Q @ (R.T @ centre) + np.array([shift, 0.0, 0.0])
        return Hypothesis(SimilarityTransform(Q, t, s), fit, 0.01)

    cfg = InitConfig(top_k=6)
    round_table = ObjectSymmetry(0, axis)
    spun = [hyp(a, 1.0, 0.0, 0.9 - a / 10) for a in (0.0, 0.5, 1.0)]
    assert len(_select(spun, cfg, round_table, centre=centre, size=size)) == 1  # one pose, spun
    larger = hyp(0.3, 1.27, 0.0, 0.95)  # ICP grown onto part of the object: the best fitness
    shifted = hyp(0.0, 1.0, 0.25 * size, 0.5)
    kept = _select([*spun, larger, shifted], cfg, round_table, centre=centre, size=size)
    assert [h.fitness for h in kept] == [0.95, 0.9, 0.5]
    near = [hyp(0.0, 1.05, 0.0, 0.8), hyp(0.0, 1.0, 0.05 * size, 0.7)]  # within 10 %: the same
    assert len(_select([spun[0], *near], cfg, round_table, centre=centre, size=size)) == 1
    with pytest.raises(ValueError, match="min_shift"):
        InitConfig(min_shift=-1.0)
