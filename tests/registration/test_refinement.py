"""Bidirectional refinement against known similarities between exact analytic fields."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from regnf.fields.analytic import (
    Box,
    Capsule,
    Cylinder,
    RoundedBox,
    Sphere,
    Transformed,
    Union,
)
from regnf.fields.field import Field
from regnf.registration.point_sets import NearestPoints
from regnf.registration.refinement import (
    RefineConfig,
    reference_length,
    refine,
    refine_many,
)
from regnf.registration.transform import SimilarityTransform

# Converges well inside the paper's 200 iterations from the start used below; the test config
# only lowers the early-stop threshold so that the 1e-3 accuracy, not the paper's stopping
# rule, decides when it ends.
TEST_CFG = RefineConfig(early_stop_residual=1e-5)


def make_library() -> Field:
    """An asymmetric, chair-like union of primitives (library field frame, about 1 unit tall)."""
    return Union(
        RoundedBox(half_extents=(0.45, 0.3, 0.06), radius=0.03, center=(0.0, 0.0, 0.5)),
        Box(half_extents=(0.05, 0.3, 0.3), center=(-0.4, 0.0, 0.85)),
        Cylinder(radius=0.05, half_height=0.22, center=(0.35, 0.22, 0.22)),
        Cylinder(radius=0.05, half_height=0.22, center=(-0.35, -0.22, 0.22)),
        Sphere(radius=0.13, center=(0.22, -0.12, 0.64)),
        Capsule(a=(0.05, 0.25, 0.6), b=(0.4, 0.25, 0.72), radius=0.04),
        name="lib",
    )


def rotation(axis: list[float], angle: float) -> np.ndarray:
    """(3, 3) rotation about ``axis`` by ``angle`` radians (Rodrigues, written out)."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def scene_for(library: Field, T_gt: SimilarityTransform) -> tuple[Field, Field]:
    """(object alone, object on a floor) in a scene frame where T_gt maps scene -> library."""
    obj = Transformed(library, T_gt.inverse().matrix(), name="placed")
    lo = float(obj.bounds[0, 2])
    size = float((obj.bounds[1] - obj.bounds[0]).max())
    # A floor slab well below the object: present in the field, never near the samples.
    floor = Box(half_extents=(5 * size, 5 * size, 0.05 * size),
                center=(0.0, 0.0, lo - 0.6 * size))
    return obj, Union(floor, obj, name="scene")


def surface_samples(field: Field, n: int, seed: int) -> torch.Tensor:
    """(n, 3) points on the zero level set: random points projected by Newton steps."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = field.bounds[0], field.bounds[1]
    x = lo + (hi - lo) * torch.rand(8 * n, 3, generator=gen)
    for _ in range(6):
        s, g = field.sdf_and_gradient(x)
        x = x - s[:, None] * g / g.norm(dim=1, keepdim=True).clamp(min=1e-9) ** 2
    ok = field.sdf(x).abs() < 1e-5
    x = x[ok]
    assert x.shape[0] >= n
    return x[:n].contiguous()


def errors(T: SimilarityTransform, T_gt: SimilarityTransform) -> tuple[float, float, float]:
    """Geodesic rotation error (rad), |t - t_gt| and |s / s_gt - 1|."""
    c = (np.trace(np.asarray(T_gt.R).T @ np.asarray(T.R)) - 1.0) / 2.0
    rot = float(np.arccos(np.clip(c, -1.0, 1.0)))
    return rot, float(np.linalg.norm(np.asarray(T.t) - np.asarray(T_gt.t))), abs(T.s / T_gt.s - 1.0)


def perturbed(T_gt: SimilarityTransform, angle: float, shift: list[float], scale: float) -> SimilarityTransform:
    """T_gt with a rotation error ``angle``, a translation error ``shift`` and scale factor."""
    R = rotation([0.3, -0.5, 0.8], angle) @ np.asarray(T_gt.R)
    return SimilarityTransform(R, np.asarray(T_gt.t) + np.asarray(shift), T_gt.s * scale)


@pytest.fixture(scope="module")
def problem() -> dict:
    lib = make_library()
    T_gt = SimilarityTransform(rotation([0.2, 0.1, 1.0], 2.1), np.array([0.1, -0.2, 0.05]), 1.3)
    obj, scene = scene_for(lib, T_gt)
    return {
        "lib": lib, "scene": scene, "T_gt": T_gt,
        "A": surface_samples(obj, 2000, seed=1), "B": surface_samples(lib, 2000, seed=2),
        "size": float((lib.bounds[1] - lib.bounds[0]).norm()),
    }


@pytest.mark.parametrize("optimizer, tolerance", [("adam", 1e-3), ("lm", 1e-5)])
def test_recovers_the_truth_from_within_the_basin(problem: dict, optimizer: str, tolerance: float) -> None:
    """Both optimisers reach the truth; Levenberg-Marquardt converges to it much more tightly."""
    size = problem["size"]
    T0 = perturbed(problem["T_gt"], 0.15, [0.05 * size, -0.02 * size, 0.01 * size], 1.07)
    res = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0,
                 replace(TEST_CFG, optimizer=optimizer))
    rot, dt, ds = errors(res.transform, problem["T_gt"])
    assert rot < tolerance and dt / size < tolerance and ds < tolerance, (rot, dt / size, ds)
    assert res.inlier_fraction > 0.99
    assert res.iterations <= max(TEST_CFG.max_iterations, TEST_CFG.lm_max_iterations)
    assert len(res.history) >= res.iterations
    h = res.history[-1]
    assert {"loss", "mean_residual_A", "mean_residual_B", "alpha", "c", "s"} <= set(h)
    assert 0.0 < h["alpha"] <= 1.0
    assert res.seconds > 0
    # Resampling grew both sets (jittered points on both surfaces), never past the cap.
    if optimizer == "lm":
        assert res.iterations <= 10  # where Adam takes about 100
    n_A = [h["n_A"] for h in res.history]
    assert n_A[0] == 2000 and n_A[-1] > 2000 and max(n_A) <= TEST_CFG.max_samples
    assert res.history[-1]["n_B"] > 2000


# Caps that make each optimiser take a fixed number of iterations (no convergence stop).
FIXED_STEPS = {
    "adam": lambda n: replace(TEST_CFG, optimizer="adam", max_iterations=n, convergence_window=0),
    "lm": lambda n: replace(TEST_CFG, optimizer="lm", lm_max_iterations=n, lm_step_tolerance=1e-30,
                            early_stop_residual=0.0),
}


@pytest.mark.parametrize("optimizer, iterations", [("adam", 40), ("lm", 13)])
def test_resampling_respects_the_cap(problem: dict, optimizer: str, iterations: int) -> None:
    T0 = perturbed(problem["T_gt"], 0.02, [0.0, 0.0, 0.0], 1.0)
    cfg = replace(FIXED_STEPS[optimizer](iterations), max_samples=2300)
    res = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0, cfg)
    assert res.history[-1]["n_A"] == 2300 and res.history[-1]["n_B"] == 2300


def test_regulariser_pulls_scene_samples_to_the_library(problem: dict) -> None:
    """On a partial scan the regulariser is the trimmed scene -> library NN distance."""
    T_gt, lib = problem["T_gt"], problem["lib"]
    A = problem["A"]
    seen = torch.as_tensor(T_gt.apply(A.double().numpy())[:, 0] > 0.0)  # the front half only
    Ap, B = A[seen], problem["B"]
    res = refine(problem["scene"], lib, Ap, B, T_gt, replace(TEST_CFG, max_iterations=1))
    # Hand computation at T_gt, brute force: mapped scene samples to their nearest library sample.
    y = torch.as_tensor(T_gt.apply(Ap.double().numpy()))
    d2 = torch.cdist(y, B.double()).min(dim=1).values ** 2 / reference_length(lib) ** 2
    keep = int(0.8 * d2.shape[0])
    expected = float(d2.sort().values[:keep].mean())
    assert res.history[0]["regulariser"] == pytest.approx(expected, rel=1e-4)
    # Library -> scene would be large here: half the library was never seen.
    back = torch.cdist(B.double(), y).min(dim=1).values ** 2 / reference_length(lib) ** 2
    assert float(back.sort().values[: int(0.8 * back.shape[0])].mean()) > 20 * expected
    # ...and the partial scan still registers.
    size = problem["size"]
    T0 = perturbed(T_gt, 0.15, [0.04 * size, 0.0, -0.02 * size], 0.95)
    res = refine(problem["scene"], lib, Ap, B, T0, TEST_CFG)
    rot, dt, ds = errors(res.transform, T_gt)
    assert rot < 2e-3 and dt / size < 1e-3 and ds < 1e-3, (rot, dt / size, ds)


def test_nearest_neighbour_backends_agree() -> None:
    gen = torch.Generator().manual_seed(7)
    pts, q = torch.rand(500, 3, generator=gen), torch.rand(300, 3, generator=gen)
    tree = NearestPoints(pts)
    brute = NearestPoints(pts)
    brute.tree = None  # the GPU path: chunked cdist
    assert torch.equal(tree.query(q), brute.query(q))
    assert torch.equal(tree.query(q), torch.cdist(q, pts).argmin(dim=1))


@pytest.mark.parametrize("scale", [0.25, 4.0])
def test_large_scale_differences(scale: float) -> None:
    lib = make_library()
    T_gt = SimilarityTransform(rotation([1.0, 0.4, 0.2], -0.7), np.array([0.3, 0.1, -0.4]), scale)
    obj, scene = scene_for(lib, T_gt)
    A, B = surface_samples(obj, 1500, seed=3), surface_samples(lib, 1500, seed=4)
    size = float((lib.bounds[1] - lib.bounds[0]).norm())
    T0 = perturbed(T_gt, 0.12, [-0.03 * size, 0.04 * size, 0.0], 0.93)
    res = refine(scene, lib, A, B, T0, TEST_CFG)
    rot, dt, ds = errors(res.transform, T_gt)
    assert rot < 1e-3 and dt / size < 1e-3 and ds < 1e-3, (rot, dt / size, ds)
    # Residuals are library distances: they do not depend on how big the scene copy is.
    assert res.mean_residual_A < 1e-3 * reference_length(lib)


@pytest.mark.parametrize("optimizer", ["adam", "lm"])
def test_the_last_step_is_returned(problem: dict, optimizer: str) -> None:
    T0 = perturbed(problem["T_gt"], 0.1, [0.02, 0.0, 0.0], 1.05)
    res = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0, FIXED_STEPS[optimizer](1))
    assert res.iterations == 1
    # One step moves every free parameter (Adam: by about its learning rate).
    assert not np.allclose(res.transform.matrix(), T0.matrix(), atol=1e-4)
    assert res.transform.s != pytest.approx(T0.s, rel=1e-4)
    assert res.history[0]["s"] == pytest.approx(T0.s)  # the history is of the evaluated step
    none = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0, FIXED_STEPS[optimizer](0))
    assert none.iterations == 0 and np.allclose(none.transform.matrix(), T0.matrix(), atol=1e-12)


@pytest.mark.parametrize("optimizer", ["adam", "lm"])
def test_fix_scale_and_one_directional(problem: dict, optimizer: str) -> None:
    T0 = perturbed(problem["T_gt"], 0.1, [0.03, -0.02, 0.0], 1.0)
    base = replace(TEST_CFG, optimizer=optimizer, max_iterations=30)
    cfg = replace(base, bidirectional=False, fix_scale=True)
    fixed = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0,
                   replace(base, fix_scale=True))
    assert fixed.transform.s == T0.s
    one = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0, cfg)
    garbage = 100.0 + 7.0 * torch.rand(50, 3, generator=torch.Generator().manual_seed(5))
    other = refine(problem["scene"], problem["lib"], problem["A"], garbage, T0, cfg)
    absent = refine(problem["scene"], problem["lib"], problem["A"], None, T0, cfg)
    for r in (other, absent):
        assert np.array_equal(r.transform.matrix(), one.transform.matrix())
        assert r.loss == one.loss
    assert one.transform.s == T0.s
    assert math.isnan(one.mean_residual_B)
    # ...and it still improves the pose.
    rot0 = errors(T0, problem["T_gt"])[0]
    assert errors(one.transform, problem["T_gt"])[0] < rot0


@pytest.mark.parametrize("optimizer", ["adam", "lm"])
def test_refine_many_picks_the_hypothesis_nearest_the_truth(problem: dict, optimizer: str) -> None:
    T_gt, size = problem["T_gt"], problem["size"]
    inits = [
        perturbed(T_gt, 2.5, [0.2 * size, 0.0, 0.1 * size], 1.2),  # far off: a wrong basin
        perturbed(T_gt, 0.1, [0.02 * size, 0.01 * size, 0.0], 1.03),  # near the truth
        perturbed(T_gt, math.pi / 2, [0.0, 0.15 * size, 0.0], 0.85),
    ]
    cfg = replace(TEST_CFG, optimizer=optimizer, max_iterations=80)
    results = refine_many(problem["scene"], problem["lib"], problem["A"], problem["B"], inits, cfg)
    assert len(results) == 3
    best = int(np.argmin([r.loss for r in results]))
    assert best == 1
    assert errors(results[1].transform, T_gt)[0] < 1e-2
    assert results[1].inlier_fraction > max(results[0].inlier_fraction, results[2].inlier_fraction)
    # Batched refinement equals refining the hypothesis alone (Adam is elementwise; LM solves,
    # accepts and fits a kernel per hypothesis).
    alone = refine(problem["scene"], problem["lib"], problem["A"], problem["B"], inits[1], cfg)
    assert np.allclose(alone.transform.matrix(), results[1].transform.matrix(), atol=1e-5)


class _NaNField(Sphere):
    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return super().sdf(x) * float("nan")


def test_bad_input(problem: dict) -> None:
    scene, lib, A, B, T = problem["scene"], problem["lib"], problem["A"], problem["B"], problem["T_gt"]
    with pytest.raises(ValueError, match="A .*empty"):
        refine(scene, lib, A[:0], B, T)
    with pytest.raises(ValueError, match="B .*empty"):
        refine(scene, lib, A, B[:0], T)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        refine(scene, lib, A[:, :2], B, T)
    with pytest.raises(ValueError, match="non-finite coordinates"):
        refine(scene, lib, torch.full_like(A, float("nan")), B, T)
    with pytest.raises(ValueError, match="non-finite SDF"):
        refine(_NaNField(), lib, A, B, T)
    with pytest.raises(ValueError, match="is on meta"):
        refine(scene, lib, A.to("meta"), B, T)
    with pytest.raises(ValueError, match="device"):
        refine(scene, lib, A, B, T, device="meta")
    with pytest.raises(ValueError, match="one device"):
        refine(Sphere().to("meta"), lib, A, B, T)
    with pytest.raises(ValueError, match="not a rotation"):
        refine(scene, lib, A, B, SimilarityTransform(2.0 * np.eye(3), np.zeros(3), 1.0))
    with pytest.raises(ValueError, match="scale"):
        refine(scene, lib, A, B, SimilarityTransform(np.eye(3), np.zeros(3), -1.0))
    with pytest.raises(ValueError, match="at least one"):
        refine_many(scene, lib, A, B, [])
    with pytest.raises(ValueError, match="trim_fraction"):
        RefineConfig(trim_fraction=0.0)
    with pytest.raises(ValueError, match="lr_rotation"):
        RefineConfig(lr_rotation=-1.0)
    with pytest.raises(ValueError, match="optimizer"):
        RefineConfig(optimizer="sgd")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="lm_damping"):
        RefineConfig(lm_damping=0.0)


class _Trainable(Field):
    """A field with a trainable offset (stands in for a neural field's weights)."""

    def __init__(self, child: Field) -> None:
        super().__init__(bounds=child.bounds, to_world=child.to_world)
        self.child = child
        self.offset = torch.nn.Parameter(torch.zeros(()))

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return self.child.sdf(x) + self.offset

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        return self.child.color(x, d)


class _Dilated(Field):
    """``child`` grown by ``eps`` field units everywhere: SDF ``child - eps``."""

    def __init__(self, child: Field, eps: float) -> None:
        super().__init__(bounds=child.bounds, to_world=child.to_world)
        self.child, self.eps = child, eps

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return self.child.sdf(x) - self.eps

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        return self.child.color(x, d)


def test_a_uniformly_dilated_scene_is_explained_by_the_offset_it_records(problem: dict) -> None:
    """Scene grown by eps: at the true pose ``S_lib(T x) = s (S_scene(x) + eps)``, so the
    offset is ``s eps / L``, reported with the result, and the pose stays at the truth."""
    T_gt, lib = problem["T_gt"], problem["lib"]
    obj, _ = scene_for(lib, T_gt)
    eps = 0.004  # scene units: well inside the offset's bound
    scene = _Dilated(obj, eps)
    A = surface_samples(scene, 2000, seed=3)
    res = refine(scene, lib, A, problem["B"], T_gt, TEST_CFG)
    expected = T_gt.s * eps / reference_length(lib)
    assert res.offset == pytest.approx(expected, rel=0.02)
    assert res.history[0]["offset"] == 0.0  # the history starts from no offset
    rot, dt, ds = errors(res.transform, T_gt)
    assert rot < 1e-4 and dt / problem["size"] < 1e-4 and ds < 1e-4, (rot, dt, ds)
    # Without the offset, the same dilation can only be absorbed by moving the pose.
    fixed = refine(scene, lib, A, problem["B"], T_gt, replace(TEST_CFG, level_set_offset=False))
    assert fixed.offset == 0.0
    assert errors(fixed.transform, T_gt)[2] > 10 * max(ds, 1e-5)


@pytest.mark.parametrize("optimizer", ["adam", "lm"])
def test_field_parameters_get_no_gradient(problem: dict, optimizer: str) -> None:
    lib = _Trainable(make_library())
    T0 = perturbed(problem["T_gt"], 0.05, [0.01, 0.0, 0.0], 1.0)
    res = refine(problem["scene"], lib, problem["A"], problem["B"], T0, FIXED_STEPS[optimizer](3))
    assert res.iterations == 3
    # Neither trained nor left with a gradient, and still trainable afterwards.
    assert lib.offset.grad is None and lib.offset.requires_grad
    assert float(lib.offset.detach()) == 0.0


@pytest.mark.parametrize("optimizer", ["adam", "lm"])
def test_same_bits_on_any_thread_count_and_the_count_is_restored(problem: dict, optimizer: str) -> None:
    """The refinement runs on one torch thread whatever the caller set (repeatable results),
    and gives the caller's setting back."""
    T0 = perturbed(problem["T_gt"], 0.1, [0.0, 0.0, 0.0], 1.05)
    cfg = replace(TEST_CFG, optimizer=optimizer, max_iterations=30)
    before = torch.get_num_threads()
    runs = []
    try:
        for n in (2, 1, 2):
            torch.set_num_threads(n)
            runs.append(refine(problem["scene"], problem["lib"], problem["A"], problem["B"], T0, cfg))
            assert torch.get_num_threads() == n
    finally:
        torch.set_num_threads(before)
    for r in runs[1:]:
        assert np.array_equal(r.transform.matrix(), runs[0].transform.matrix())
        assert r.inlier_fraction == runs[0].inlier_fraction


def test_lm_jacobian_matches_finite_differences(problem: dict) -> None:
    """The Jacobian written out in ``linearise`` against central differences of the residuals
    under the same local updates (rotation, log scale, translation, offset latent)."""
    from regnf.registration.refine_batch import HypothesisBatch

    T0 = perturbed(problem["T_gt"], 0.1, [0.02, -0.01, 0.0], 1.04)
    A, B = problem["A"].double(), problem["B"].double()
    cfg = replace(TEST_CFG, max_offset=0.01, trim_fraction=1.0)
    batch = HypothesisBatch(problem["scene"], problem["lib"], A, B, [T0], cfg)
    with torch.no_grad():
        batch.delta[0] = 0.004  # off zero, so that the offset's tanh bound matters
    lin = batch.linearise()
    state = batch.pose_state()
    eps = 1e-6
    numeric = []
    for j in range(8):
        diffs = []
        for sign in (1.0, -1.0):
            step = torch.zeros(1, 8, dtype=torch.float64)
            step[0, j] = sign * eps
            batch.apply_step(step)
            diffs.append(batch.linearise())
            batch.restore_pose(state, torch.ones(1, dtype=torch.bool))
        numeric.append((diffs[0].x - diffs[1].x) / (2 * eps))
        # Regulariser vectors (all kept, in sample order): equal but where a nearest
        # neighbour switches under the perturbation.
        fd = (diffs[0].q - diffs[1].q) / (2 * eps)
        close = ((lin.Jq[:, :, j] - fd).abs() <= 1e-6 + 1e-4 * fd.abs()).all(dim=1)
        assert float(close.double().mean()) > 0.995, (j, float(close.double().mean()))
    torch.testing.assert_close(lin.J, torch.stack(numeric, dim=1), rtol=1e-4, atol=1e-6)


def test_a_hypothesis_heading_for_a_better_ones_pose_stops(problem: dict) -> None:
    """Two starts at one pose: from the merge iteration on the later one stops (the earlier one
    wins the tie) and the earlier one still reaches the truth; with merging off both run on."""
    T_gt, size = problem["T_gt"], problem["size"]
    T0 = perturbed(T_gt, 0.15, [0.05 * size, -0.02 * size, 0.01 * size], 1.07)
    cfg = replace(TEST_CFG, lm_prune_after=2)
    first, second = refine_many(problem["scene"], problem["lib"], problem["A"], problem["B"], [T0, T0], cfg)
    assert second.iterations == cfg.lm_prune_after + 1 < first.iterations
    rot, dt, ds = errors(first.transform, T_gt)
    assert rot < 1e-5 and dt / size < 1e-5 and ds < 1e-5
    off = replace(cfg, lm_merge_rotation_deg=0.0)
    both = refine_many(problem["scene"], problem["lib"], problem["A"], problem["B"], [T0, T0], off)
    assert both[0].iterations == both[1].iterations == first.iterations
    # A start half a turn away is another pose of an asymmetric object: never merged.
    flipped = SimilarityTransform(rotation([0, 0, 1], math.pi) @ np.asarray(T0.R), T0.t, T0.s)
    apart = refine_many(problem["scene"], problem["lib"], problem["A"], problem["B"], [T0, flipped], cfg)
    assert apart[1].iterations > cfg.lm_prune_after + 1 or apart[1].inlier_fraction < 0.5


def test_motion_about_a_continuous_symmetry_axis_is_no_motion() -> None:
    """Turning a pose about the library's symmetry axis (through its bounds' centre) moves it
    by nothing modulo a continuous symmetry, and by the turn without one; a tilt or a shift
    along the axis still counts."""
    from regnf.registration.metrics import ObjectSymmetry
    from regnf.registration.refine_batch import HypothesisBatch

    lib = Cylinder(radius=0.4, half_height=0.3, center=(0.1, -0.2, 0.3))
    A = surface_samples(lib, 500, seed=3)
    batch = HypothesisBatch(lib, lib, A, A, [SimilarityTransform(np.eye(3), np.zeros(3), 1.0)], TEST_CFG)
    before = batch.pose_snapshot()
    axis, centre = np.array([0.0, 0.0, 1.0]), lib.bounds.double().mean(dim=0).numpy()
    round_table = ObjectSymmetry(0, axis)

    def moved_by(R: np.ndarray, shift: np.ndarray) -> tuple[float, float, float, float]:
        with torch.no_grad():  # the pose x -> R (x - centre) + centre + shift, as the new base pose
            batch.R0[0] = torch.as_tensor(R)
            batch.t0[0] = torch.as_tensor(centre - R @ centre + shift)
        plain, sym = batch.motion(before), batch.motion(before, round_table)
        return float(plain[0][0]), float(plain[1][0]), float(sym[0][0]), float(sym[1][0])

    turn = moved_by(rotation([0, 0, 1], 0.7), np.zeros(3))
    assert turn[0] == pytest.approx(0.7, abs=1e-9) and turn[1] > 0.01
    assert turn[2] < 1e-6 and turn[3] < 1e-9
    tilt = moved_by(rotation([1, 0, 0], 0.05), np.zeros(3))
    assert tilt[2] == pytest.approx(0.05, abs=1e-6)
    lift = moved_by(np.eye(3), np.array([0.0, 0.0, 0.02]))
    assert lift[3] == pytest.approx(0.02 / batch.L, rel=1e-6)


@pytest.mark.cuda
@pytest.mark.parametrize("optimizer, tolerance", [("adam", 1e-3), ("lm", 1e-5)])
def test_refinement_on_the_device_recovers_the_truth(problem: dict, optimizer: str, tolerance: float,
                                                     device: str) -> None:
    size = problem["size"]
    T0 = perturbed(problem["T_gt"], 0.15, [0.05 * size, -0.02 * size, 0.01 * size], 1.07)
    res = refine(problem["scene"].to(device), problem["lib"].to(device), problem["A"].to(device),
                 problem["B"].to(device), T0, replace(TEST_CFG, optimizer=optimizer))
    rot, dt, ds = errors(res.transform, problem["T_gt"])
    assert rot < tolerance and dt / size < tolerance and ds < tolerance, (rot, dt / size, ds)
    assert res.inlier_fraction > 0.99
