"""RANSAC for a similarity from correspondences, against known similarities."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from regnf.registration.ransac import draws_needed, fit_similarities, ransac_similarity


def known_similarity(seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    return Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3), float(rng.uniform(0.5, 2.0))


def test_closed_form_fit_recovers_each_row_of_a_batch() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(5, 6, 3))
    truths = [known_similarity(k) for k in range(5)]
    dst = np.stack([s * p @ R.T + t for p, (R, t, s) in zip(src, truths)])
    R, t, s = fit_similarities(src, dst)
    for k, (R0, t0, s0) in enumerate(truths):
        assert np.allclose(R[k], R0, atol=1e-9) and np.allclose(t[k], t0, atol=1e-9)
        assert s[k] == pytest.approx(s0, rel=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_a_mirrored_target_still_gives_a_rotation() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(1, 8, 3))
    R, _, s = fit_similarities(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(R[0]) == pytest.approx(1.0) and s[0] > 0


def clouds_with_matches(n: int, inliers: float, seed: int):
    """A cloud, its image under a known similarity, and matches of which a share are right.

    The scale stays within 4 % of 1, as between the initialisation's pre-scaled clouds: the
    edge-length check compares lengths across the clouds."""
    rng = np.random.default_rng(seed)
    R, t, _ = known_similarity(seed)
    s = float(rng.uniform(0.96, 1.04))
    source = rng.uniform(-1.0, 1.0, size=(n, 3))
    target = s * source @ R.T + t
    j = np.arange(n)
    wrong = rng.random(n) >= inliers
    j[wrong] = rng.integers(0, n, size=int(wrong.sum()))
    return source, target, np.stack([np.arange(n), j], axis=1), (R, t, s)


def test_recovers_the_similarity_among_mostly_wrong_matches() -> None:
    source, target, corr, (R, t, s) = clouds_with_matches(400, 0.3, 2)
    res = ransac_similarity(source, target, corr, distance=0.02 * s, seed=0)
    assert res is not None and res.fitness == pytest.approx(1.0)
    assert np.allclose(res.matrix[:3, :3], s * R, atol=1e-6) and np.allclose(res.matrix[:3, 3], t, atol=1e-6)


def test_the_same_hypothesis_on_any_thread_count_and_for_the_same_seed() -> None:
    source, target, corr, (_, _, s) = clouds_with_matches(300, 0.15, 3)
    runs = [ransac_similarity(source, target, corr, 0.02 * s, seed=5, workers=w) for w in (1, 2, 1)]
    assert all(np.array_equal(r.matrix, runs[0].matrix) and r.iterations == runs[0].iterations for r in runs)


def test_all_right_matches_stop_after_the_first_batch() -> None:
    source, target, corr, (_, _, s) = clouds_with_matches(200, 1.0, 4)
    res = ransac_similarity(source, target, corr, 0.02 * s, batch=500, max_iterations=100_000)
    assert res is not None and res.iterations == 500


def test_nothing_when_no_draw_passes_the_checks_or_there_are_too_few_matches() -> None:
    source, target, corr, _ = clouds_with_matches(50, 1.0, 6)
    collapsed = corr.copy()
    collapsed[:, 1] = 0  # every match points at one target point: no edge agrees
    assert ransac_similarity(source, target, collapsed, 0.05, max_iterations=2000) is None
    assert ransac_similarity(source, target, corr[:3], 0.05) is None


def test_the_stopping_rule_holds_for_tiny_and_whole_shares() -> None:
    # The textbook count: log(1 - confidence) / log(1 - share**n).
    assert draws_needed(0.5, 4, 0.999) == pytest.approx(math.log(0.001) / math.log(1 - 0.5**4))
    # One match in 50 000 agrees: share**4 = 1.6e-19 is below the float's resolution next to
    # 1, where 1 - share**4 rounds to 1 and the textbook formula divides by zero.
    tiny = draws_needed(2e-5, 4, 0.999)
    assert math.isfinite(tiny) and tiny == pytest.approx(-math.log(0.001) / 2e-5**4, rel=1e-6)
    assert draws_needed(1.0, 4, 0.999) == 0.0 and draws_needed(0.0, 4, 0.999) == math.inf


def test_scoring_a_chunk_at_a_time_gives_the_same_hypothesis(monkeypatch: pytest.MonkeyPatch) -> None:
    # Clean matches pass the checks by the thousand: the scoring bounds its memory by moving
    # the source points for a chunk of hypotheses at a time, which must not change the choice.
    from regnf.registration import ransac

    source, target, corr, (_, _, s) = clouds_with_matches(300, 0.6, 8)
    whole = ransac_similarity(source, target, corr, 0.02 * s, seed=3)
    monkeypatch.setattr(ransac, "SCORE_POINTS", 7 * len(source))
    chunked = ransac_similarity(source, target, corr, 0.02 * s, seed=3)
    assert np.array_equal(whole.matrix, chunked.matrix) and whole.iterations == chunked.iterations


def test_preemptive_scoring_scores_few_hypotheses_on_every_point(monkeypatch: pytest.MonkeyPatch) -> None:
    # A batch's hypotheses are ranked on an evenly spread subset and only the best few are
    # scored on every point; the result is the known similarity, as without preemption.
    from regnf.registration import ransac

    source, target, corr, (R, t, s) = clouds_with_matches(2000, 0.3, 9)
    calls: list[tuple[int, int]] = []
    scores = ransac._scores

    def counting(points, tree, Rs, *args, **kwargs):
        calls.append((len(points), len(Rs)))
        return scores(points, tree, Rs, *args, **kwargs)

    monkeypatch.setattr(ransac, "_scores", counting)
    fast = ransac_similarity(source, target, corr, 0.02 * s, seed=1, preempt_points=256, preempt_keep=3)
    assert any(n < len(source) for n, _ in calls), "no batch was ranked on the subset"
    assert all(h <= 3 for n, h in calls if n == len(source))
    calls.clear()
    full = ransac_similarity(source, target, corr, 0.02 * s, seed=1, preempt_points=0)
    assert all(n == len(source) for n, _ in calls)
    for res in (fast, full):
        assert res is not None and res.fitness == pytest.approx(1.0)
        assert np.allclose(res.matrix[:3, :3], s * R, atol=1e-6) and np.allclose(res.matrix[:3, 3], t, atol=1e-6)
    with pytest.raises(ValueError, match="preempt"):
        ransac_similarity(source, target, corr, 0.02 * s, preempt_keep=0)
