"""OrientedBox: construction, corners round trip, similarity mapping, containment, and the
exact SDF, box coordinates and bounds of torch points."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from regnf.fields.oriented_box import OrientedBox, OrientedBoxes
from tests.registration.fixtures import placement, rot


def test_aabb_basics() -> None:
    box = OrientedBox.from_aabb(np.array([-1.0, 0.0, 2.0]), np.array([1.0, 4.0, 3.0]))
    np.testing.assert_allclose(box.center, [0.0, 2.0, 2.5])
    np.testing.assert_allclose(box.half_extents, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(box.rotation, np.eye(3))
    assert box.radius == pytest.approx(np.sqrt(1 + 4 + 0.25))
    assert box.diagonal == pytest.approx(2 * np.sqrt(5.25))
    c = box.corners()
    assert c.shape == (8, 3)
    np.testing.assert_allclose(c.min(axis=0), [-1.0, 0.0, 2.0])
    np.testing.assert_allclose(c.max(axis=0), [1.0, 4.0, 3.0])


@pytest.mark.parametrize("half", [(0.3, 0.5, 0.7), (0.5, 0.5, 0.5), (1.0, 1.0, 0.01)])
def test_from_corners_round_trip_any_order(half: tuple[float, float, float]) -> None:
    # Equal sides (a cube) would defeat a PCA; a thin slab tests the near-degenerate case.
    R = rot([1.0, 2.0, -0.5], 0.9)
    box = OrientedBox(np.array([0.3, -1.0, 2.0]), np.array(half), R)
    corners = box.corners()[np.random.default_rng(3).permutation(8)]
    back = OrientedBox.from_corners(corners)
    np.testing.assert_allclose(back.center, box.center, atol=1e-12)
    # Same box: same corner set and the same points inside.
    d = np.linalg.norm(back.corners()[:, None] - box.corners()[None], axis=-1)
    assert d.min(axis=1).max() < 1e-9
    assert np.linalg.det(back.rotation) == pytest.approx(1.0)
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, (2000, 3)) + box.center
    np.testing.assert_array_equal(back.contains(pts), box.contains(pts))


def test_from_corners_of_aabb_gives_identity() -> None:
    box = OrientedBox.from_aabb(np.zeros(3), np.array([1.0, 2.0, 3.0]))
    back = OrientedBox.from_corners(box.corners()[::-1])
    np.testing.assert_allclose(back.rotation, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(back.half_extents, [0.5, 1.0, 1.5])


def test_from_corners_rejects_non_boxes() -> None:
    box = OrientedBox.from_aabb(np.zeros(3), np.ones(3))
    c = box.corners()
    with pytest.raises(ValueError, match="8, 3"):
        OrientedBox.from_corners(c[:7])
    skewed = c.copy()
    skewed[:, 0] += 0.3 * skewed[:, 2]  # a parallelepiped, not a box
    with pytest.raises(ValueError, match="rectangular box"):
        OrientedBox.from_corners(skewed)
    flat = c.copy()
    flat[:, 2] = 0.0  # all corners coplanar
    with pytest.raises(ValueError, match="rectangular box|same point"):
        OrientedBox.from_corners(flat)
    with pytest.raises(ValueError, match="same point"):
        OrientedBox.from_corners(np.zeros((8, 3)))


def test_degenerate_boxes_raise() -> None:
    with pytest.raises(ValueError, match="hi > lo"):
        OrientedBox.from_aabb(np.zeros(3), np.array([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="half_extents"):
        OrientedBox(np.zeros(3), np.array([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="proper rotation"):
        OrientedBox(np.zeros(3), np.ones(3), np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="center"):
        OrientedBox(np.array([0.0, np.nan, 0.0]), np.ones(3))


def test_transformed_maps_corners_and_containment() -> None:
    box = OrientedBox(np.array([0.1, 0.2, 0.3]), np.array([0.2, 0.4, 0.6]), rot([0, 0, 1], 0.4))
    M = placement([1.0, 1.0, 0.0], 1.1, [2.0, -1.0, 0.5], 0.25)
    moved = box.transformed(M)
    mapped = box.corners() @ M[:3, :3].T + M[:3, 3]
    np.testing.assert_allclose(moved.corners(), mapped, atol=1e-12)
    np.testing.assert_allclose(moved.half_extents, 0.25 * box.half_extents)
    pts = np.random.default_rng(1).uniform(-1, 1, (3000, 3))
    np.testing.assert_array_equal(moved.contains(pts @ M[:3, :3].T + M[:3, 3]), box.contains(pts))
    with pytest.raises(ValueError):
        box.transformed(np.diag([1.0, 2.0, 1.0, 1.0]))  # non-uniform scale


def test_contains_padding() -> None:
    box = OrientedBox.from_aabb(-np.ones(3), np.ones(3))
    p = np.array([[1.05, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -1.2, 0.0]])
    np.testing.assert_array_equal(box.contains(p), [False, True, False])
    np.testing.assert_array_equal(box.contains(p, pad_rel=0.1), [True, True, False])
    np.testing.assert_allclose(box.inflated(0.1).half_extents, 1.1)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        box.contains(np.zeros(3))


def test_json_round_trip() -> None:
    box = OrientedBox(np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3]), rot([0, 1, 0], 0.3))
    back = OrientedBox.from_json(box.to_json())
    for a, b in zip(back, box):
        np.testing.assert_allclose(a, b)


def test_torch_sdf_is_the_exact_distance_and_the_bounds_are_tight() -> None:
    box = OrientedBox(np.array([0.3, -0.2, 0.5]), np.array([0.2, 0.4, 0.1]), rot([1, 2, 3], 0.7))
    rng = np.random.default_rng(2)
    x = rng.uniform(-1.5, 1.5, (4000, 3))
    # Truth by construction: outside, the distance to the nearest point of the box (box
    # coordinates clamped to the half extents); inside, minus the distance to the nearest face.
    u = box.to_local(x)
    inside = box.contains(x)
    nearest = np.clip(u, -box.half_extents, box.half_extents)
    truth = np.where(inside, -(box.half_extents - np.abs(u)).min(axis=1),
                     np.linalg.norm(u - nearest, axis=1))
    got = box.sdf(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(got, truth, atol=1e-12)
    assert np.all((got <= 0) == inside)
    # float32 points on the box's surface: |sdf| at float32 precision, in the points' dtype.
    c32 = torch.from_numpy(box.corners()).float()
    assert box.sdf(c32).dtype == torch.float32 and float(box.sdf(c32).abs().max()) < 1e-6
    np.testing.assert_allclose(box.local(torch.from_numpy(x)).numpy(), u, atol=1e-12)
    lo, hi = box.aabb().numpy()
    np.testing.assert_allclose(lo, box.corners().min(axis=0), atol=1e-12)
    np.testing.assert_allclose(hi, box.corners().max(axis=0), atol=1e-12)


def _truth(box: OrientedBox, x: np.ndarray) -> np.ndarray:
    """The exact distance of ``x`` (n, 3) to ``box`` by construction (as above)."""
    u = box.to_local(x)
    nearest = np.clip(u, -box.half_extents, box.half_extents)
    return np.where(box.contains(x), -(box.half_extents - np.abs(u)).min(axis=1),
                    np.linalg.norm(u - nearest, axis=1))


def test_many_boxes_at_once_give_each_box_its_exact_distance() -> None:
    boxes = [OrientedBox(np.array([0.3, -0.2, 0.5]), np.array([0.2, 0.4, 0.1]), rot([1, 2, 3], 0.7)),
             OrientedBox(np.array([-0.6, 0.1, 0.0]), np.array([0.05, 0.3, 0.6]), rot([0, 0, 1], -1.2)),
             OrientedBox(np.zeros(3), np.array([1.0, 1.0, 1.0]))]
    x = np.random.default_rng(3).uniform(-1.5, 1.5, (3000, 3))
    many = OrientedBoxes(boxes)
    got = many.sdf(torch.from_numpy(x))
    assert got.shape == (3, 3000) and len(many) == 3
    for k, box in enumerate(boxes):
        np.testing.assert_allclose(got[k].numpy(), _truth(box, x), atol=1e-12)
    got32 = many.sdf(torch.from_numpy(x).float())
    assert got32.dtype == torch.float32
    np.testing.assert_allclose(got32.numpy(), got.numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="at least one box"):
        OrientedBoxes([])


def test_from_bounds_is_the_mapped_aabb() -> None:
    M = placement([0.0, 0.0, 1.0], 0.9, [1.0, -2.0, 0.25], 1.7)
    bounds = torch.tensor([[-0.5, -0.25, 0.0], [0.5, 0.75, 1.0]], dtype=torch.float64)
    box = OrientedBox.from_bounds(bounds, torch.from_numpy(M))
    ref = OrientedBox.from_aabb(bounds[0].numpy(), bounds[1].numpy()).transformed(M)
    for a, b in zip(box, ref):
        np.testing.assert_allclose(a, b, atol=1e-12)
    # A tensor box (float32, any device) converts to the float64 arrays.
    t = OrientedBox(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.5, 0.5, 0.5]))
    assert t.center.dtype == np.float64 and np.array_equal(t.rotation, np.eye(3))
