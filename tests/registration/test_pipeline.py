"""End-to-end ``register`` and the baselines on analytic fields with a known similarity."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from regnf.fields.analytic import Box, Cylinder, Transformed, Union
from regnf.fields.oriented_box import OrientedBox
from regnf.fields.similarity import similarity_matrix
from regnf.registration.baselines import (
    kabsch,
    register_fgr,
    register_init_only,
    register_nerf2nerf,
)
from regnf.registration.metrics import geodesic_angle
from regnf.registration.pipeline import RegistrationConfig, register
from regnf.registration.transform import SimilarityTransform
from tests.core.helpers import torch_threads

from .fixtures import OBJECT_HI, OBJECT_LO, make_object, make_scene, placement, rot

DIAG = float(np.linalg.norm(OBJECT_HI - OBJECT_LO))


def library_at_scale(factor: float):
    """The test object in a library frame ``factor`` times larger than metres."""
    return Transformed(make_object(), np.asarray(similarity_matrix(np.eye(3), np.zeros(3), factor)),
                       name="lib", label="chair")


def scene_and_truth(yaw: float, factor: float):
    """A scene with the object placed by a yaw + translation, and T_gt scene -> library."""
    M = placement([0, 0, 1], yaw, [0.7, -0.4, 0.0], 1.0)
    scene = make_scene(M)
    proposal = OrientedBox.from_corners(
        (np.array([[x, y, z] for x in (OBJECT_LO[0], OBJECT_HI[0]) for y in (OBJECT_LO[1], OBJECT_HI[1])
                   for z in (OBJECT_LO[2], OBJECT_HI[2])]) @ M[:3, :3].T) + M[:3, 3]
    )
    S = np.asarray(similarity_matrix(np.eye(3), np.zeros(3), factor))
    truth = SimilarityTransform.from_matrix(S @ np.linalg.inv(M))
    return scene, proposal, truth


def errors(T: SimilarityTransform, truth: SimilarityTransform) -> tuple[float, float, float]:
    rot_err = geodesic_angle(truth.R.T @ T.R)
    centre = truth.apply(((OBJECT_LO + OBJECT_HI) / 2)[None])[0]
    # Translation error: where the two transforms put the object's centre, in metres.
    trans = np.linalg.norm(T.inverse().apply(centre[None]) - truth.inverse().apply(centre[None])) / DIAG
    return float(rot_err), float(trans), abs(T.s / truth.s - 1.0)


@pytest.mark.parametrize("factor", [0.25, 1.0, 4.0])
def test_register_recovers_a_known_similarity_at_any_library_scale(factor: float) -> None:
    scene, proposal, truth = scene_and_truth(2.3, factor)
    result = register(scene, library_at_scale(factor), proposal)
    r, t, s = errors(result.transform, truth)
    assert r < 0.02 and t < 0.01 and s < 0.01, (r, t, s)
    assert result.accepted and result.confidence > 0.9
    assert set(result.timings) >= {"sampling", "initialisation", "refinement", "total"}
    assert result.hypotheses and result.hypotheses[0].confidence == result.confidence
    # The whole object lies in its box at the right pose: the confidence is the SDF evidence.
    assert result.losses["containment"] == 1.0 and result.losses["seen_free"] == 0.0
    assert result.confidence == result.losses["inlier_fraction"]


def test_same_registration_on_one_thread_or_two() -> None:
    # On two threads the scene and library sampling, and each pair of field queries of the
    # screening and the refinement, run side by side, each on one thread: the same bits.
    scene, proposal, _ = scene_and_truth(2.3, 1.0)
    library = library_at_scale(1.0)
    runs = []
    for n in (1, 2):
        with torch_threads(n):
            runs.append(register(scene, library, proposal))
            assert torch.get_num_threads() == n
    one, two = runs
    assert np.array_equal(one.transform.matrix(), two.transform.matrix())
    assert one.confidence == two.confidence
    assert [h.initial.matrix().tolist() for h in one.hypotheses] == [h.initial.matrix().tolist() for h in two.hypotheses]
    assert np.array_equal(one.samples[0], two.samples[0]) and np.array_equal(one.samples[1], two.samples[1])


def test_wrong_object_is_detected() -> None:
    # A table-like object (slab on one pillar) in the proposal, the chair-like object as library.
    table = Union(Box(half_extents=(0.4, 0.4, 0.03), center=(0.0, 0.0, 0.72)),
                  Cylinder(radius=0.06, half_height=0.35, center=(0.0, 0.0, 0.35)),
                  Box(half_extents=(3.0, 3.0, 0.05), center=(0.0, 0.0, -0.05)))
    proposal = OrientedBox.from_aabb(np.array([-0.4, -0.4, 0.0]), np.array([0.4, 0.4, 0.75]))
    result = register(table, library_at_scale(1.0), proposal)
    assert not result.accepted
    assert result.confidence < RegistrationConfig().acceptance_threshold


def test_empty_proposal_box_raises() -> None:
    scene, _, _ = scene_and_truth(0.5, 1.0)
    empty = OrientedBox.from_aabb(np.array([2.0, 2.0, 0.5]), np.array([2.5, 2.5, 1.0]))
    with pytest.raises(ValueError, match="no surface"):
        register(scene, library_at_scale(1.0), empty)


def test_non_finite_field_raises() -> None:
    scene, proposal, _ = scene_and_truth(0.5, 1.0)

    class Broken(type(scene)):
        def sdf(self, x: torch.Tensor) -> torch.Tensor:
            return torch.full_like(x[:, 0], float("nan"))

    broken = Broken.__new__(Broken)
    broken.__dict__.update(scene.__dict__)
    with pytest.raises(ValueError, match="non-finite"):
        register(broken, library_at_scale(1.0), proposal)


def test_mismatched_devices_raise() -> None:
    scene, proposal, _ = scene_and_truth(0.5, 1.0)
    lib = library_at_scale(1.0).to("meta")
    with pytest.raises(ValueError, match="device"):
        register(scene, lib, proposal)


def test_baselines_run_and_nerf2nerf_keeps_unit_scale() -> None:
    scene, proposal, truth = scene_and_truth(1.0, 1.0)
    lib = library_at_scale(1.0)
    cfg = RegistrationConfig()
    # Keypoints are picked among these library points: the corners of the base slab.
    surface = np.array([[x, y, z] for x in (-0.4, 0.4) for y in (-0.25, 0.25) for z in (0.0, 0.1)])
    n2n = register_nerf2nerf(scene, lib, proposal, cfg, truth, surface, keypoint_noise_rel=0.0)
    assert n2n.transform.s == pytest.approx(1.0)
    r, t, _ = errors(n2n.transform, truth)
    assert r < 0.05 and t < 0.05, (r, t)
    init = register_init_only(scene, lib, proposal, cfg)
    fgr = register_fgr(scene, lib, proposal, cfg)
    assert init.method == "regnf-init" and fgr.method == "fgr"
    assert 0.0 <= init.confidence <= 1.0 and 0.0 <= fgr.confidence <= 1.0


def test_kabsch_recovers_a_rigid_transform() -> None:
    R = rot([0.3, -0.5, 0.8], 1.1)
    src = np.random.default_rng(0).normal(size=(6, 3))
    dst = src @ R.T + np.array([0.2, -1.0, 3.0])
    T = kabsch(src, dst)
    assert np.allclose(T.R, R, atol=1e-12) and np.allclose(T.t, [0.2, -1.0, 3.0], atol=1e-12)


def test_single_hypothesis_config_refines_one() -> None:
    from regnf.registration.pipeline import single_hypothesis

    cfg = single_hypothesis(RegistrationConfig())
    assert cfg.init.top_k == 1
    assert dataclasses.replace(cfg).init.top_k == 1


def test_a_confident_first_hypothesis_spares_refining_the_others() -> None:
    """The first hypothesis refined alone and confident enough: the others are not refined and
    the result is the one refining every hypothesis picks; below the bar, every one competes."""
    scene, proposal, truth = scene_and_truth(2.3, 1.0)
    library = library_at_scale(1.0)
    every = register(scene, library, proposal, RegistrationConfig(confident_score=2.0))
    first = register(scene, library, proposal, RegistrationConfig(confident_score=0.85))
    assert len(every.hypotheses) > 1 and len(first.hypotheses) == 1
    assert every.confidence >= 0.85 and first.confidence == every.confidence
    assert np.allclose(first.transform.matrix(), every.transform.matrix(), atol=1e-6)
    r, t, s = errors(first.transform, truth)
    assert r < 0.02 and t < 0.01 and s < 0.01
    # A bar above the first's confidence refines them all again.
    again = register(scene, library, proposal, RegistrationConfig(confident_score=first.confidence + 1e-6))
    assert len(again.hypotheses) == len(every.hypotheses)


def test_library_samples_taken_earlier_give_the_same_registration() -> None:
    """Reusing the library's samples (discovery's refit) is the same registration, bit for bit,
    as sampling them again."""
    from regnf.core.threads import one_thread
    from regnf.registration.pipeline import sample_pair

    scene, proposal, truth = scene_and_truth(2.3, 1.0)
    library = library_at_scale(1.0)
    cfg = RegistrationConfig()
    with one_thread():  # as register and discovery sample: the same bits on any thread count
        _, lib_samples = sample_pair(scene, library, proposal, cfg)
    again = register(scene, library, proposal, cfg)
    reused = register(scene, library, proposal, cfg, library_samples=lib_samples)
    assert np.array_equal(again.transform.matrix(), reused.transform.matrix())
    assert again.confidence == reused.confidence
    assert np.array_equal(again.samples[1], reused.samples[1])
    r, t, s = errors(reused.transform, truth)
    assert r < 0.02 and t < 0.01 and s < 0.01


@pytest.mark.cuda
def test_register_on_the_device_recovers_a_known_similarity(device: str) -> None:
    scene, proposal, truth = scene_and_truth(2.3, 1.0)
    result = register(scene.to(device), library_at_scale(1.0).to(device), proposal)
    r, t, s = errors(result.transform, truth)
    assert r < 0.02 and t < 0.01 and s < 0.01, (r, t, s)
    assert result.accepted and result.confidence > 0.9
