"""Seen free: the share of a placed object's observed samples that stand where the views saw nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from regnf.fields.analytic import Sphere
from regnf.observations.visibility import VisibilityGrid
from regnf.registration.free_space import seen_free_fraction
from regnf.registration.transform import SimilarityTransform

MARGIN = 0.02


def sphere_points(n: int, radius: float, center=(0.0, 0.0, 0.0)) -> np.ndarray:
    d = np.random.default_rng(0).normal(size=(n, 3))
    return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def shifted(dx: float) -> SimilarityTransform:
    """Scene -> library: the library object stands ``dx`` along x in the scene."""
    return SimilarityTransform(np.eye(3), np.array([-dx, 0.0, 0.0]), 1.0)


def seen_below(x_max: float, scene: Sphere) -> VisibilityGrid:
    """Two views saw every voxel whose centre has x below ``x_max``, none beyond."""
    lo, hi = scene.bounds.numpy()
    n = 64
    centres = lo[0] + (np.arange(n) + 0.5) * (hi[0] - lo[0]) / n
    counts = torch.zeros((n, n, n), dtype=torch.uint8)
    counts[torch.as_tensor(centres < x_max)] = 2
    return VisibilityGrid(counts, scene.bounds)


def test_an_object_on_the_scene_surface_is_not_in_free_space() -> None:
    scene = Sphere(radius=0.5)
    points = sphere_points(2000, 0.5)
    assert seen_free_fraction(scene, points, SimilarityTransform.identity(), MARGIN) == 0.0


def test_an_object_in_empty_space_is_wholly_in_free_space() -> None:
    # A small ball placed beside the scene's sphere: every point is farther than the margin.
    scene = Sphere(radius=0.5)
    points = sphere_points(500, 0.1)
    assert seen_free_fraction(scene, points, shifted(0.8), MARGIN) == 1.0


def test_the_fraction_is_the_share_beyond_the_margin() -> None:
    # A ball of radius 0.2 centred on the scene sphere's surface at x = 0.5: its points outside
    # the scene sphere by more than the margin are counted, against the exact count.
    scene = Sphere(radius=0.5, center=(0.0, 0.0, 0.0))
    points = sphere_points(4000, 0.2)
    placed = points + np.array([0.5, 0.0, 0.0])
    expected = float(np.mean(np.linalg.norm(placed, axis=1) - 0.5 > MARGIN))
    assert 0.2 < expected < 0.8
    assert seen_free_fraction(scene, points, shifted(0.5), MARGIN) == pytest.approx(expected, abs=1e-9)


def test_only_observed_samples_count() -> None:
    # The same ball, with the views having seen only x < 0.5: the samples beyond say nothing.
    scene = Sphere(radius=0.5)
    scene.visibility = seen_below(0.5, scene)
    points = sphere_points(4000, 0.2)
    placed = points + np.array([0.5, 0.0, 0.0])
    weights = scene.visibility.observed(torch.as_tensor(placed, dtype=torch.float32)).double().numpy()
    free = np.linalg.norm(placed, axis=1) - 0.5 > MARGIN
    expected = float((weights * free).sum() / weights.sum())
    got = seen_free_fraction(scene, points, shifted(0.5), MARGIN)
    assert got == pytest.approx(expected, abs=1e-6)
    assert got != pytest.approx(float(free.mean()), abs=0.02)
    # Wholly in unobserved space: no evidence either way.
    assert seen_free_fraction(scene, sphere_points(500, 0.05), shifted(0.75), MARGIN) == 0.0


def test_scale_and_rotation_of_the_transform_are_followed() -> None:
    # The library's unit sphere scaled by 0.5 onto the scene's sphere: on the surface; by 0.3:
    # 0.2 inside it (not in free space); by 0.7: 0.2 outside, in free space.
    scene = Sphere(radius=0.5)
    points = sphere_points(1000, 1.0)
    theta = 0.7
    R = np.array([[math.cos(theta), -math.sin(theta), 0], [math.sin(theta), math.cos(theta), 0], [0, 0, 1]])
    for size, expected in ((0.5, 0.0), (0.3, 0.0), (0.7, 1.0)):
        T = SimilarityTransform(R, np.zeros(3), 1.0 / size)  # scene -> library
        assert seen_free_fraction(scene, points, T, MARGIN) == expected


def test_rejects_empty_points() -> None:
    with pytest.raises(ValueError, match="library_points"):
        seen_free_fraction(Sphere(), np.zeros((0, 3)), SimilarityTransform.identity(), MARGIN)


def test_the_confidence_is_charged_for_the_share_in_seen_free_space() -> None:
    # scored(): inlier fraction x containment x (1 - seen free); a margin of inf leaves it out.
    import dataclasses

    from regnf.fields.oriented_box import OrientedBox
    from regnf.registration.pipeline import RegistrationConfig, scored
    from regnf.registration.refinement import RefineResult

    scene = Sphere(radius=0.5)
    points = sphere_points(4000, 0.2)
    T = shifted(0.5)
    refined = RefineResult(transform=T, loss=0.0, mean_residual_A=0.0, mean_residual_B=0.0,
                           inlier_fraction=0.9, iterations=0, history=[], seconds=0.0)
    box = OrientedBox(np.zeros(3), np.full(3, 2.0), np.eye(3))
    config = RegistrationConfig()
    free = seen_free_fraction(scene, points, T, config.free_space_margin_m)
    confidence, inside, reported = scored(refined, points, box, config, scene)
    assert inside == 1.0 and reported == free and 0.2 < free < 0.8
    assert confidence == pytest.approx(0.9 * (1.0 - free), abs=1e-12)
    off = dataclasses.replace(config, free_space_margin_m=math.inf)
    assert scored(refined, points, box, off, scene) == (0.9, 1.0, 0.0)


@pytest.mark.parametrize("margin", [0.0, -0.02, math.nan])
def test_a_margin_that_is_not_positive_is_refused(margin: float) -> None:
    from regnf.registration.pipeline import RegistrationConfig

    with pytest.raises(ValueError, match="free_space_margin_m must be > 0"):
        RegistrationConfig(free_space_margin_m=margin)
