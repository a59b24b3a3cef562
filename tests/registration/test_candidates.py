"""Object candidates with no boxes, against an analytic room whose objects' boxes are known."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from regnf.fields.analytic import Box, Cylinder, Sphere, Transformed, Union
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.candidates import CandidateConfig, box_iou, find_candidates, upright_box


def yaw_matrix(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    M = np.eye(4)
    M[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    M[:3, 3] = t
    return M


# The room: 5 x 4 m floor, 2.5 m walls 10 cm thick, no ceiling; objects stand on the floor.
ROOM = [
    Box((2.6, 2.1, 0.05), (0.0, 0.0, -0.05)),  # floor
    Box((0.05, 2.1, 1.25), (-2.55, 0.0, 1.25)), Box((0.05, 2.1, 1.25), (2.55, 0.0, 1.25)),
    Box((2.6, 0.05, 1.25), (0.0, -2.05, 1.25)), Box((2.6, 0.05, 1.25), (0.0, 2.05, 1.25)),
]
# name -> (field, true box in metres)
OBJECTS = {
    "cabinet": (Transformed(Box((0.3, 0.2, 0.45), (0.0, 0.0, 0.45)), yaw_matrix(0.5, (-1.2, 0.8, 0.0))),
                OrientedBox((-1.2, 0.8, 0.45), (0.3, 0.2, 0.45), yaw_matrix(0.5, (0, 0, 0))[:3, :3])),
    "round table": (Cylinder(0.45, 0.36, (1.0, -0.6, 0.36)),
                    OrientedBox((1.0, -0.6, 0.36), (0.45, 0.45, 0.36))),
    "table": (Union(Box((0.6, 0.35, 0.02), (0.6, 1.2, 0.73)), *[Box((0.03, 0.03, 0.355), (x, y, 0.355))
                    for x in (0.05, 1.15) for y in (0.9, 1.5)]),
              OrientedBox((0.6, 1.2, 0.375), (0.6, 0.35, 0.375))),
    "ball": (Sphere(0.2, (-1.0, -1.2, 0.2)), OrientedBox((-1.0, -1.2, 0.2), (0.2, 0.2, 0.2))),
}


ROUND = {"round table": 0.45, "ball": 0.2}  # radii


@pytest.fixture(scope="module")
def found():
    room = Union(*ROOM, *(f for f, _ in OBJECTS.values()))
    return find_candidates(room, CandidateConfig(resolution=160))


def test_every_object_is_one_candidate_whose_box_matches_its_own(found) -> None:
    boxes = [c.box for c in found.candidates]
    assert len(boxes) == len(OBJECTS), f"{len(boxes)} candidates for {len(OBJECTS)} objects"
    for name, (_, truth) in OBJECTS.items():
        ious = [box_iou(b, truth) for b in boxes]
        best = boxes[int(np.argmax(ious))]
        if name in ROUND:  # any yaw is as good: the square of its diameter
            np.testing.assert_allclose(best.half_extents[:2], ROUND[name], atol=0.015)
            assert max(ious) >= 0.6, f"{name}: best IoU {max(ious):.2f}"
        else:
            assert max(ious) >= 0.8, f"{name}: best IoU {max(ious):.2f}"


def test_the_floor_and_the_walls_are_the_supports_and_nothing_else(found) -> None:
    # Both faces of the floor slab and of each wall (no views: the analytic field has them all).
    level = sorted(round(p.offset / p.normal[2], 2) for p in found.supports if abs(p.normal[2]) > 0.99)
    upright = sorted(round(abs(p.offset), 2) for p in found.supports if abs(p.normal[2]) < 0.01)
    assert level == [-0.1, 0.0]  # not the table top at 0.75, nor the cabinet's at 0.9
    assert upright == [2.0, 2.0, 2.1, 2.1, 2.5, 2.5, 2.6, 2.6]
    assert len(found.supports) == 10


def test_a_turned_box_gets_its_own_axes() -> None:
    rng = np.random.default_rng(1)
    truth = OrientedBox((0.3, -0.2, 0.5), (0.4, 0.15, 0.5), yaw_matrix(1.1, (0, 0, 0))[:3, :3])
    u = rng.uniform(-1, 1, size=(4000, 3))
    u[np.arange(4000), rng.integers(0, 3, 4000)] = rng.choice([-1.0, 1.0], 4000)  # on the faces
    pts = (u * truth.half_extents) @ truth.rotation.T + truth.center
    box = upright_box(pts, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(np.sort(box.half_extents), np.sort(truth.half_extents), atol=1e-6)
    np.testing.assert_allclose(box.center, truth.center, atol=1e-6)
    assert box_iou(box, truth) > 0.97
    assert np.isclose(np.linalg.det(box.rotation), 1.0)


def test_box_iou_of_known_overlaps() -> None:
    a = OrientedBox((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    assert box_iou(a, a) == pytest.approx(1.0)
    half = OrientedBox((1.0, 0.0, 0.0), (1.0, 1.0, 1.0))  # overlaps a's half: 4 / (8 + 8 - 4)
    assert box_iou(a, half) == pytest.approx(1 / 3, abs=0.02)
    far = OrientedBox((5.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    assert box_iou(a, far) == 0.0
    turned = OrientedBox((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), yaw_matrix(math.pi / 4, (0, 0, 0))[:3, :3])
    # a square turned by 45 degrees inside the same square: the overlap is an octagon of area 8 (sqrt2 - 1)
    inter = 8 * (math.sqrt(2) - 1) * 2
    assert box_iou(a, turned) == pytest.approx(inter / (16 - inter), abs=0.02)


def test_a_field_with_no_objects_has_no_candidates() -> None:
    empty = Union(*ROOM)
    got = find_candidates(empty, CandidateConfig(resolution=120))
    assert got.candidates == []
    assert torch.is_tensor(empty.to_world)


@pytest.mark.parametrize("seen_below", [False, True])
def test_a_top_whose_underside_no_view_saw_grows_to_the_floor(seen_below: bool) -> None:
    from regnf.observations.visibility import VisibilityGrid

    # A table top floating 0.7 m above the floor (its legs unseen, so not in the field).
    room = Union(*ROOM, Box((0.45, 0.45, 0.02), (0.5, -0.5, 0.72)))
    lo, hi = np.array([-2.7, -2.2, -0.2]), np.array([2.7, 2.2, 2.6])
    res = np.array([54, 44, 28])  # 10 cm voxels
    counts = torch.full(tuple(res), 255, dtype=torch.uint8)
    if not seen_below:  # no view saw under the top
        centres = lo + (np.stack(np.meshgrid(*[np.arange(r) for r in res], indexing="ij"), -1) + 0.5) * (hi - lo) / res
        under = (np.abs(centres[..., 0] - 0.5) < 0.5) & (np.abs(centres[..., 1] + 0.5) < 0.5) & (centres[..., 2] < 0.65)
        counts[torch.as_tensor(under)] = 0
    room.visibility = VisibilityGrid(counts, np.stack([lo, hi]))
    got = find_candidates(room, CandidateConfig(resolution=160))
    assert len(got.candidates) == 1
    box = got.candidates[0].box
    bottom, top = box.center[2] - box.half_extents[2], box.center[2] + box.half_extents[2]
    assert top == pytest.approx(0.74, abs=0.02)
    assert bottom == pytest.approx(0.7 if seen_below else 0.0, abs=0.02)
