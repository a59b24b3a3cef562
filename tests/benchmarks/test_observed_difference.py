"""What tells two shapes apart, read against a visibility grid whose observed half is known."""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from regnf.benchmarks.observed_difference import observed_difference
from regnf.fields.analytic import Sphere
from regnf.observations.visibility import VisibilityGrid

BOUNDS = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])


def _scene_seen_below_x0() -> Sphere:
    """A scene whose views saw (twice) everything with x < 0 and nothing with x > 0."""
    n = 40
    centres_x = BOUNDS[0, 0] + (np.arange(n) + 0.5) * (BOUNDS[1, 0] - BOUNDS[0, 0]) / n
    counts = torch.zeros((n, n, n), dtype=torch.uint8)
    counts[torch.as_tensor(centres_x < 0.0)] = 2
    scene = Sphere(radius=0.1)
    scene.visibility = VisibilityGrid(counts, torch.as_tensor(BOUNDS, dtype=torch.float32))
    return scene


def _chair_and_variant(bump_x: float) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """A body, and the same body with a bump centred at ``bump_x``: they differ at the bump."""
    body = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    bump = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    bump.apply_translation((bump_x, 0.0, 0.25))
    return body, trimesh.util.concatenate([body, bump])


def test_a_difference_where_no_view_looked_reads_unobserved_and_one_in_view_observed() -> None:
    scene = _scene_seen_below_x0()
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.3, 0.0)  # the placement moves both shapes, keeping x
    body, unseen_bump = _chair_and_variant(bump_x=0.6)
    assert observed_difference(scene, pose, unseen_bump, body) == 0.0
    assert observed_difference(scene, pose, body, unseen_bump) == 0.0
    body, seen_bump = _chair_and_variant(bump_x=-0.6)
    assert observed_difference(scene, pose, seen_bump, body) == 1.0
    # A placement that moves the unseen bump into the observed half reads it observed.
    pose[:3, 3] = (-1.2, 0.0, 0.0)
    assert observed_difference(scene, pose, unseen_bump, body) == 1.0


def test_identical_shapes_have_no_difference_and_a_scene_without_a_grid_saw_everything() -> None:
    body, variant = _chair_and_variant(bump_x=0.6)
    scene = _scene_seen_below_x0()
    assert math.isnan(observed_difference(scene, np.eye(4), body, body.copy()))
    scene.visibility = None
    assert observed_difference(scene, np.eye(4), variant, body) == 1.0
