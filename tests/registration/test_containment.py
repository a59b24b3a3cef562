"""``containment``: the fraction of a library object that a transform maps into a box."""

from __future__ import annotations

import numpy as np
import pytest

from regnf.fields.oriented_box import OrientedBox
from regnf.registration.containment import containment
from regnf.registration.transform import SimilarityTransform

from .fixtures import rot


def grid(n: int) -> np.ndarray:
    """(n^3, 3) cell centres of a regular grid over [0, 1]^3."""
    c = (np.arange(n) + 0.5) / n
    return np.stack(np.meshgrid(c, c, c, indexing="ij"), axis=-1).reshape(-1, 3)


def test_counts_the_points_a_known_similarity_puts_in_the_box() -> None:
    # Library points on a 10^3 grid over [0, 1]^3; the scene -> library map y = s R x + t.
    R, t, s = rot([0.3, -0.5, 0.8], 1.1), np.array([0.2, -0.7, 1.5]), 2.5
    T = SimilarityTransform(R, t, s)
    Y = grid(10)
    X = (Y - t) @ R / s  # where each library point is in the scene
    # A box, in the scene, that holds exactly the library points with y_x < 0.3 (3 of 10 layers):
    # the library slab [0, 0.3] x [0, 1] x [0, 1] mapped into the scene (with a little room).
    lo, hi = np.array([-0.01, -0.01, -0.01]), np.array([0.3, 1.01, 1.01])
    centre_lib, half_lib = (lo + hi) / 2, (hi - lo) / 2
    box = OrientedBox((centre_lib - t) @ R / s, half_lib / s, R.T)
    assert containment(Y, T, box) == pytest.approx(0.3)
    assert box.contains(X).sum() == 300  # the same count, independently of containment()


def test_all_and_nothing() -> None:
    T = SimilarityTransform(np.eye(3), np.zeros(3), 1.0)
    Y = grid(4)
    assert containment(Y, T, OrientedBox.from_aabb(np.full(3, -0.1), np.full(3, 1.1))) == 1.0
    assert containment(Y, T, OrientedBox.from_aabb(np.full(3, 2.0), np.full(3, 3.0))) == 0.0
    # Scaling the library up by 2 (s = 0.5 maps scene to library) doubles the object in the scene.
    half = SimilarityTransform(np.eye(3), np.zeros(3), 0.5)
    assert containment(Y, half, OrientedBox.from_aabb(np.zeros(3), np.ones(3))) == pytest.approx(1 / 8)


def test_rejects_empty_or_misshapen_points() -> None:
    T = SimilarityTransform(np.eye(3), np.zeros(3), 1.0)
    box = OrientedBox.from_aabb(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="non-empty"):
        containment(np.zeros((0, 3)), T, box)
    with pytest.raises(ValueError, match="non-empty"):
        containment(np.zeros((5, 2)), T, box)
