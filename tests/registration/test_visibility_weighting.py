"""Registration weighs evidence by where the scene's views observed space.

A scene seen from -x only: the object's far side was never observed, and there the scene
field holds made-up geometry (a blob, as a field trained from few views extrapolates). With
the observation record the refinement ignores the blob and keeps the true pose with a
confident score; without it the blob's residuals count and the confidence drops. A pose that
puts library surface where the views saw free space is still charged for it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh

from regnf.fields.analytic import Box, Sphere, Union
from regnf.observations.visibility import VisibilityGrid
from regnf.registration.metrics import geodesic_angle
from regnf.registration.pipeline import RegistrationConfig, sample_pair, sample_tensors
from regnf.registration.refinement import RefineConfig, refine, without_steps
from regnf.registration.transform import SimilarityTransform

from .fixtures import make_object, make_scene, object_box, placement

M = placement([0, 0, 1], 0.4, [0.3, -0.2, 0.0], 1.0)  # object -> scene (metres = field units)
SEEN_BELOW_X = 0.3  # the views saw everything with x below this (the object's centre)


def seen_from_minus_x(bounds: np.ndarray, resolution: int = 96) -> VisibilityGrid:
    """Counts of 2 views in the half space x < SEEN_BELOW_X, none beyond."""
    lo, hi = bounds
    n = np.maximum(1, np.round(resolution * (hi - lo) / (hi - lo).max())).astype(int)
    centres_x = lo[0] + (np.arange(n[0]) + 0.5) * (hi[0] - lo[0]) / n[0]
    counts = torch.zeros(tuple(n), dtype=torch.uint8)
    counts[torch.as_tensor(centres_x < SEEN_BELOW_X)] = 2
    return VisibilityGrid(counts, torch.as_tensor(bounds, dtype=torch.float32))


@pytest.fixture(scope="module")
def setting() -> dict:
    clean = make_scene(M)
    # Made-up geometry on the unobserved far side of the object (x > 0.55), inside its box.
    blob = Sphere(radius=0.18, center=(0.62, -0.05, 0.35))
    scene = Union(clean, blob, label="scene", name="room")
    bounds = np.array([[-1.5, -1.5, -0.2], [1.5, 1.5, 1.2]])
    library = make_object()
    proposal = object_box().transformed(M).inflated(0.1)
    sampling = dataclasses.replace(RegistrationConfig().scene_sampling, rays_per_side=40)
    cfg = RegistrationConfig(scene_sampling=sampling, library_sampling=sampling)
    scene_s, lib_s = sample_pair(scene, library, proposal, cfg)
    A, B = sample_tensors(scene_s, lib_s, library.device)
    truth = SimilarityTransform.from_matrix(np.linalg.inv(M))
    return {"scene": scene, "library": library, "A": A, "B": B, "truth": truth,
            "grid": seen_from_minus_x(bounds)}


def _errors(T: SimilarityTransform, truth: SimilarityTransform) -> tuple[float, float]:
    return float(geodesic_angle(np.asarray(T.R) @ np.asarray(truth.R).T)), float(np.linalg.norm(T.t - truth.t))


def test_unobserved_made_up_geometry_is_no_evidence(setting: dict) -> None:
    scene, library, A, B, truth = (setting[k] for k in ("scene", "library", "A", "B", "truth"))
    cfg = RefineConfig(max_iterations=30)
    blind = refine(scene, library, A, B, truth, cfg)
    scene.visibility = setting["grid"]
    try:
        seeing = refine(scene, library, A, B, truth, cfg)
        ignored = refine(scene, library, A, B, truth, dataclasses.replace(cfg, use_visibility=False))
    finally:
        scene.visibility = None
    assert ignored.inlier_fraction == pytest.approx(blind.inlier_fraction)  # the switch turns it off
    assert seeing.inlier_fraction > blind.inlier_fraction + 0.05
    assert seeing.inlier_fraction > 0.9
    rot, shift = _errors(seeing.transform, truth)
    assert rot < 0.01 and shift < 0.01


def test_library_surface_put_into_observed_free_space_still_counts(setting: dict) -> None:
    scene, library, A, B, truth = (setting[k] for k in ("scene", "library", "A", "B", "truth"))
    # The object turned by 180 degrees about its vertical axis, about its own centre: the far
    # half of the library now lands on the observed side, partly in free space.
    c = np.array([0.0, 0.0, 0.375])
    turn = placement([0, 0, 1], np.pi, (c - placement([0, 0, 1], np.pi, [0, 0, 0], 1.0)[:3, :3] @ c).tolist(), 1.0)
    flipped = SimilarityTransform.from_matrix(turn @ np.linalg.inv(M))
    cfg = RefineConfig(max_iterations=0)  # score the two poses as they are
    scene.visibility = setting["grid"]
    try:
        true_score = refine(scene, library, A, B, truth, cfg).inlier_fraction
        flip_score = refine(scene, library, A, B, flipped, cfg).inlier_fraction
    finally:
        scene.visibility = None
    assert flip_score < true_score - 0.2


def _slab_seen_from_above() -> dict:
    """A 40 mm slab whose top (z = 0) the views saw from above: the grid counts space down to
    its margin (2 voxels, 0.1) below the top as observed, so its underside (z = -0.04) lies in
    "observed" space though no view saw it; the scene field fills everything under the top."""
    library = Box(half_extents=(0.4, 0.4, 0.02), center=(0.0, 0.0, -0.02))
    scene = Box(half_extents=(0.4, 0.4, 0.5), center=(0.0, 0.0, -0.5))  # top and sides, filled
    bounds = np.array([[-1.0, -1.0, -1.2], [1.0, 1.0, 0.8]])
    n = 40  # 0.05 voxels
    centres_z = bounds[0, 2] + (np.arange(n) + 0.5) * (bounds[1, 2] - bounds[0, 2]) / n
    counts = torch.zeros((n, n, n), dtype=torch.uint8)
    counts[:, :, torch.as_tensor(centres_z > -0.1)] = 2
    scene.visibility = VisibilityGrid(counts, torch.as_tensor(bounds, dtype=torch.float32))
    mesh = trimesh.creation.box(extents=(0.8, 0.8, 0.04))
    mesh.apply_translation((0.0, 0.0, -0.02))
    B, faces = trimesh.sample.sample_surface(mesh, 3000, seed=0)
    under = mesh.face_normals[faces][:, 2] < -0.9
    xy = np.stack(np.meshgrid(np.linspace(-0.35, 0.35, 30), np.linspace(-0.35, 0.35, 30)), -1).reshape(-1, 2)
    A = np.concatenate([xy, np.zeros((xy.shape[0], 1))], axis=1)  # the scene's seen top
    return {"scene": scene, "library": library, "A": torch.as_tensor(A, dtype=torch.float32),
            "B": torch.as_tensor(B, dtype=torch.float32), "under": float(under.mean())}


def test_a_back_face_within_the_grids_margin_is_read_in_front_and_carries_no_weight() -> None:
    s = _slab_seen_from_above()
    cfg = without_steps(RefineConfig())  # score the true pose as it is
    truth = SimilarityTransform.identity()
    ahead = refine(s["scene"], s["library"], s["A"], s["B"], truth, cfg)
    at_sample = refine(s["scene"], s["library"], s["A"], s["B"], truth,
                       dataclasses.replace(cfg, visibility_lookahead=0.0))
    # Top and sides fit the scene; the underside is 0.04 inside the fill (an outlier) and
    # unobserved. Read at the sample it counts: the library's inliers are the rest of its area.
    assert at_sample.inlier_fraction_library == pytest.approx(1.0 - s["under"], abs=0.03)
    # Read in front of it (3 voxels below), it is unobserved and no evidence either way.
    assert ahead.inlier_fraction_library > 0.98
    assert ahead.inlier_fraction_scene == pytest.approx(at_sample.inlier_fraction_scene)
