"""The sensor noise model and the SLAM-like pose error against closed forms and analytic scenes.

Every depth image here is analytic (a plane, a ramp, a step), so the truth each piece is held to
(Nguyen et al.'s sigma, the disparity grid, the speckle rate, the incidence angle, the drift's
end) is computed in the test, independently of the module.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from regnf.captures.depth_uncertainty import DepthNoiseModel
from regnf.captures.model import check_rigid_pose
from regnf.synthetic.cache import non_default
from regnf.synthetic.capture import RoomCaptureConfig, capture_room
from regnf.synthetic.pose_noise import PoseNoiseConfig, perturb_poses
from regnf.synthetic.sensor_noise import (
    NOISE_LEVELS,
    TRUE_POSES_NAME,
    SensorNoiseConfig,
    apply_sensor_noise,
    depth_noise_model,
    incidence_angles,
)


def _nguyen_sigma(z: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Nguyen, Izadi, Lovell 2012: axial sigma in metres (z metres, theta radians)."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2 + 0.0001 / np.sqrt(z) * theta**2 / (np.pi / 2 - theta) ** 2


def _K(f: float, w: int, h: int) -> np.ndarray:
    return np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])


def _plane(z0: float, theta0_deg: float, K: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """z-depth (H, W) of a plane through (0, 0, z0) turned by theta0 about the camera y axis, and
    each pixel's incidence angle (radians)."""
    th = np.radians(theta0_deg)
    n = np.array([np.sin(th), 0.0, -np.cos(th)])
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    depth = (n @ [0.0, 0.0, z0]) / (rays @ n)  # ray parameter = z-depth (ray z = 1)
    theta = np.arccos(np.abs(rays @ n) / np.linalg.norm(rays, axis=-1))
    return depth, theta


def _grey(h: int, w: int) -> np.ndarray:
    return np.full((h, w, 3), 128, np.uint8)


@pytest.mark.parametrize(("z0", "theta0"), [(1.0, 0.0), (2.5, 45.0), (1.5, 60.0)])
def test_axial_sigma_matches_nguyen_closed_form(z0: float, theta0: float) -> None:
    w = h = 24
    K = _K(2000.0, w, h)  # narrow view: z and theta nearly constant over the plane
    depth, theta = _plane(z0, theta0, K, w, h)
    # The angle the model uses, from the depth alone, is the plane's.
    np.testing.assert_allclose(incidence_angles(depth, K), theta, atol=1e-5)
    rng = np.random.default_rng(1)
    cfg = SensorNoiseConfig(axial_scale=1.0)
    residuals = np.stack([apply_sensor_noise(depth, None, _grey(h, w), K, rng, cfg)[0] - depth
                          for _ in range(300)])
    assert abs(residuals.mean()) < 0.02 * _nguyen_sigma(z0, np.radians(theta0))
    assert residuals.std() == pytest.approx(_nguyen_sigma(z0, np.radians(theta0)), rel=0.05)
    # Per pixel too: the residual in units of the pixel's own closed-form sigma is standard normal.
    assert (residuals / _nguyen_sigma(depth, theta)).std() == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize("focal", [580.0, 179.0])
def test_lateral_jitter_is_half_a_depth_camera_pixel_at_normal_incidence(focal: float) -> None:
    """ICL-NUIM's 0.5 pixel is a pixel of the depth camera (580 px focal length): the same
    jitter in metres, 0.5 z / 580, whatever focal length the image is rendered with."""
    w, h = 64, 48
    K = _K(focal, w, h)
    slope = 0.01  # metres per column: bilinear resampling of a ramp is exact
    depth = np.broadcast_to(1.0 + slope * np.arange(w), (h, w)).copy()
    facing = np.broadcast_to([0.0, 0.0, -1.0], (h, w, 3))
    rng = np.random.default_rng(2)
    cfg = SensorNoiseConfig(lateral_scale=0.625)  # x Nguyen's 0.8 px = ICL-NUIM's 0.5 px
    assert cfg.disparity_focal_px == 580.0
    shifts = np.stack([(apply_sensor_noise(depth, facing, _grey(h, w), K, rng, cfg)[0] - depth) / slope
                       for _ in range(100)])[:, :, 4:-4]  # away from the clamped border
    assert shifts.std() == pytest.approx(0.5 * focal / 580.0, rel=0.05)
    # The model a capture made with this sensor names has that sigma, in the image's pixels.
    assert depth_noise_model(cfg, focal).lateral_px == pytest.approx(shifts.std(), rel=0.05)


@pytest.mark.parametrize("level", ["sensor", "harsh"])
def test_a_levels_depth_model_has_the_axial_sigma_it_draws(level: str) -> None:
    """harsh draws twice Nguyen et al.'s sigma: the model its captures name is that sigma, in
    closed form, at every depth and angle, with the default weights."""
    model = depth_noise_model(NOISE_LEVELS[level], 179.0)
    z, theta = np.array([0.5, 1.0, 2.5, 4.0]), np.radians([0.0, 30.0, 60.0, 75.0])
    factor = {"sensor": 1.0, "harsh": 2.0}[level]
    np.testing.assert_allclose(model.sigma(z, theta), factor * _nguyen_sigma(z, theta), rtol=1e-12)
    assert (model.reference_m, model.min_weight) == (DepthNoiseModel().reference_m, DepthNoiseModel().min_weight)


def test_disparity_quantisation_steps_are_b_f_over_d() -> None:
    w, h = 64, 64
    K = _K(200.0, w, h)
    depth = np.linspace(1.0, 3.0, w * h).reshape(h, w)
    facing = np.broadcast_to([0.0, 0.0, -1.0], (h, w, 3))
    cfg = SensorNoiseConfig(disparity_step_px=1 / 8)
    out = apply_sensor_noise(depth, facing, _grey(h, w), K, np.random.default_rng(0), cfg)[0].astype(np.float64)
    bf = 0.075 * 580.0  # the Kinect-like baseline and infrared focal length
    disparity = bf / out
    steps = disparity * 8
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)  # on the 1/8 pixel grid
    assert np.abs(disparity - bf / depth).max() <= 1 / 16 + 1e-4  # the nearest grid value
    levels = np.unique(np.round(steps))
    np.testing.assert_array_equal(np.diff(levels), 1.0)  # consecutive levels, none skipped
    # Millimetre quantisation on top: every depth a whole number of millimetres.
    mm = apply_sensor_noise(depth, facing, _grey(h, w), K, np.random.default_rng(0),
                            dataclasses.replace(cfg, depth_step_m=0.001))[0].astype(np.float64) * 1000
    np.testing.assert_allclose(mm, np.round(mm), atol=2e-3)


def test_speckle_fraction() -> None:
    w, h = 64, 64
    K = _K(100.0, w, h)
    depth = np.full((h, w), 2.0)
    rng = np.random.default_rng(3)
    cfg = SensorNoiseConfig(speckle=0.1)
    lost = np.stack([apply_sensor_noise(depth, None, _grey(h, w), K, rng, cfg)[0] == 0 for _ in range(10)])
    n = lost.size
    assert abs(lost.mean() - 0.1) < 4 * np.sqrt(0.1 * 0.9 / n)
    kept = np.stack([apply_sensor_noise(depth, None, _grey(h, w), K, rng, SensorNoiseConfig())[0]])
    np.testing.assert_array_equal(kept[0], depth.astype(np.float32))  # no speckle: nothing lost


def test_no_return_at_grazing_angles() -> None:
    w, h = 64, 64
    K = _K(200.0, w, h)  # incidence 70-88 degrees across the plane
    depth, theta = _plane(1.5, 79.0, K, w, h)
    assert np.degrees(theta).min() < 72 and np.degrees(theta).max() > 86
    cfg = SensorNoiseConfig(max_incidence_deg=80.0)
    out = apply_sensor_noise(depth, None, _grey(h, w), K, np.random.default_rng(0), cfg)[0]
    deg = np.degrees(theta)
    assert np.all(out[deg > 80.2] == 0)
    np.testing.assert_array_equal(out[deg < 79.8], depth[deg < 79.8].astype(np.float32))


@pytest.mark.parametrize("width", [1, 2, 5])
def test_incidence_beside_depth_edges_is_that_of_the_pixels_own_surface(width: int) -> None:
    """A fronto-parallel bar ``width`` pixels wide before a fronto-parallel wall: every pixel,
    at the bar's edges too, faces the camera (the neighbours across the edge are another
    surface); a plane's angle stays exact up to the image border."""
    w, h = 40, 30
    K = _K(100.0, w, h)
    depth = np.full((h, w), 3.0)
    depth[:, 20 : 20 + width] = 1.0
    depth[10, 5:8] = 0.0  # a hole: its neighbours face the camera as well
    theta = incidence_angles(depth, K)
    # Fronto-parallel: the angle between the ray and the optical axis.
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    off_axis = np.arctan(np.hypot((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]))
    np.testing.assert_allclose(theta[depth > 0], off_axis[depth > 0], atol=1e-9)
    plane, truth = _plane(1.5, 75.0, K, w, h)
    np.testing.assert_allclose(incidence_angles(plane, K), truth, atol=1e-6)


def test_no_return_at_depth_edges_and_beyond_range() -> None:
    w, h = 32, 32
    K = _K(40.0, w, h)
    depth = np.where(np.arange(w) < 16, 1.0, 2.0) * np.ones((h, 1))
    depth[5, 5] = 0.0  # a hole: its neighbours border no return
    depth[:, 28:] = 9.0  # beyond the range
    # A depth camera of the image's own focal length: a band of one image pixel each side.
    cfg = SensorNoiseConfig(edge_jump_footprints=12.0, max_range_m=8.0, disparity_focal_px=40.0)
    out = apply_sensor_noise(depth, None, _grey(h, w), K, np.random.default_rng(0), cfg)[0]
    lost = out == 0
    cols = np.arange(w)
    near_step = (np.abs(cols - 15.5) < 1) | (np.abs(cols - 27.5) < 1)
    assert lost[:, near_step].all() and lost[:, 28:].all()
    assert lost[4:7, 4:7].all()
    expected_kept = ~near_step[None, :] & (cols < 28)
    expected_kept = expected_kept & np.ones((h, 1), bool)
    expected_kept[4:7, 4:7] = False
    np.testing.assert_array_equal(out[expected_kept], depth[expected_kept].astype(np.float32))
    # A slanted plane (up to 70 degrees here) is no edge.
    plane, theta = _plane(1.0, 50.0, K, w, h)
    assert np.degrees(theta).max() > 70
    kept = apply_sensor_noise(plane, None, _grey(h, w), K, np.random.default_rng(0), cfg)[0]
    np.testing.assert_array_equal(kept, plane.astype(np.float32))


@pytest.mark.parametrize("f_image", [40.0, 100.0, 145.0, 400.0, 1000.0])
def test_edge_band_is_the_depth_camera_pixels_wide_in_metres(f_image: float) -> None:
    """Beside a straight step, the lost width on each side is ``edge_band_px`` pixels of the
    depth camera (f = 400 px) converted to metres: whole rings of image pixels where the image is
    finer, a share of the edge pixels where it is coarser."""
    w, h = 48, 400
    K = _K(f_image, w, h)
    z_near, step = 1.0, 24
    depth = np.where(np.arange(w) < step, z_near, 2.0) * np.ones((h, 1))
    cfg = SensorNoiseConfig(edge_jump_footprints=12.0, disparity_focal_px=400.0, edge_band_px=1.0)
    out = apply_sensor_noise(depth, None, _grey(h, w), K, np.random.default_rng(1), cfg)[0]
    lost = out == 0
    # Lost width per side in pixels of the image, averaged over the rows: 400 / f_image of a
    # depth-camera pixel is one image pixel, so the band is f_image / 400 image pixels wide.
    band = f_image / 400.0
    near_side = lost[:, :step].sum(1).mean()
    far_side = lost[:, step:].sum(1).mean()
    part = band - np.floor(band)  # the ring lost pixel by pixel: a binomial share
    tol = 4.0 * np.sqrt(part * (1 - part) / h) + 1e-9
    assert abs(near_side - band) <= tol and abs(far_side - band) <= tol
    # Only pixels within the band's rings of the step are lost; the rest keep the clean depth.
    cols = np.arange(w)
    far_from_step = (cols < step - int(np.ceil(band))) | (cols >= step + int(np.ceil(band)))
    np.testing.assert_array_equal(out[:, far_from_step], depth[:, far_from_step].astype(np.float32))


def test_lateral_jitter_never_reports_a_depth_between_two_surfaces() -> None:
    """Jittered across a step from 1 m to 2 m, a pixel reads one side or the other; within a
    slanted plane it reads the plane (bilinear, off the pixel's own depth)."""
    w, h = 40, 200
    K = _K(100.0, w, h)
    depth = np.where(np.arange(w) < 20, 1.0, 2.0) * np.ones((h, 1))
    # A depth camera four times coarser than the image: a jitter of ~1.6 image pixels.
    cfg = SensorNoiseConfig(lateral_scale=0.5, disparity_focal_px=25.0)
    out = apply_sensor_noise(depth, None, _grey(h, w), K, np.random.default_rng(3), cfg)[0]
    on_a_side = np.isclose(out, 1.0) | np.isclose(out, 2.0) | (out == 0)
    assert on_a_side.all()
    assert (out[:, 18:22] != depth[:, 18:22]).any()  # the jitter did cross the step
    plane, _ = _plane(1.5, 40.0, K, w, h)
    moved = apply_sensor_noise(plane, None, _grey(h, w), K, np.random.default_rng(3), cfg)[0]
    inner = (slice(5, -5), slice(5, -5))
    assert not np.allclose(moved[inner], plane[inner])
    assert moved[inner].min() >= plane.min() - 1e-6 and moved[inner].max() <= plane.max() + 1e-6


def test_exposure_gain_is_one_per_frame() -> None:
    rgb = np.random.default_rng(0).integers(20, 120, (8, 8, 3)).astype(np.uint8)
    depth = np.ones((8, 8))
    out = apply_sensor_noise(depth, None, rgb, _K(10.0, 8, 8), np.random.default_rng(4),
                             SensorNoiseConfig(exposure_sigma=0.1))[1]
    assert out.dtype == np.uint8 and not np.array_equal(out, rgb)
    gain = out.astype(np.float64) / rgb
    assert np.ptp(gain) < 1.0 / 20 + 1e-9  # one gain, up to rounding to whole levels


def _random_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = rng.uniform(-3, 3, (n, 3))
    return out


def _errors(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error (m) and rotation angle (degrees) of est against true, from the trace."""
    rel = est[:, :3, :3] @ np.swapaxes(true[:, :3, :3], 1, 2)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.linalg.norm(est[:, :3, 3] - true[:, :3, 3], axis=1), np.degrees(np.arccos(cos))


@pytest.mark.parametrize("level", ["slam", "harsh"])
def test_drift_ends_at_the_levels_magnitude(level: str) -> None:
    pose = NOISE_LEVELS[level].pose
    assert (pose.drift_m, pose.drift_deg) == {"slam": (0.01, 0.3), "harsh": (0.03, 1.0)}[level]
    true = _random_poses(60, np.random.default_rng(5))
    drift_only = dataclasses.replace(pose, jitter_m=0.0, jitter_deg=0.0)
    est = perturb_poses(true, drift_only, np.random.default_rng(6))
    for p in est:
        check_rigid_pose(p)
    pos, ang = _errors(est, true)
    assert pos[0] == 0 and ang[0] < 1e-6  # anchored at the first frame
    assert pos[-1] == pytest.approx(pose.drift_m, rel=1e-9)
    assert ang[-1] == pytest.approx(pose.drift_deg, rel=1e-6)
    assert np.all(pos[1:-1] > 0)
    # With the jitter, the end is the drift give or take a few jitters.
    pos, ang = _errors(perturb_poses(true, pose, np.random.default_rng(6)), true)
    assert abs(pos[-1] - pose.drift_m) < 4 * pose.jitter_m
    assert abs(ang[-1] - pose.drift_deg) < 4 * pose.jitter_deg


def test_jitter_magnitude() -> None:
    pose = NOISE_LEVELS["sensor"].pose
    assert (pose.jitter_m, pose.jitter_deg, pose.drift_m, pose.drift_deg) == (0.001, 0.05, 0.0, 0.0)
    true = _random_poses(4000, np.random.default_rng(7))
    pos, ang = _errors(perturb_poses(true, pose, np.random.default_rng(8)), true)
    assert np.sqrt(np.mean(pos**2)) == pytest.approx(0.001, rel=0.05)
    assert np.sqrt(np.mean(ang**2)) == pytest.approx(0.05, rel=0.05)
    assert np.array_equal(perturb_poses(true, PoseNoiseConfig(), np.random.default_rng(8)), true)


ROOM = RoomCaptureConfig(width=32, height=24, n_views=4, coverage="low", heldout_every=0, progress=False)

SETTINGS_BEFORE_NOISE = ["width", "height", "focal", "focal_over_width", "n_views", "coverage", "seed",
                         "heldout_every", "margin", "progress"]
"""The keys of an ideal capture's ``regnf.config`` block: no noise settings, so that the bytes
(which key the fields trained on the capture) stay those of the noise-free generator."""


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_ideal_capture_is_unchanged_and_noisy_one_keeps_true_poses(tmp_path: Path) -> None:
    # The cache key of a default capture holds no noise setting (a room's cache folder stays).
    assert non_default(RoomCaptureConfig(coverage="low")) == {"coverage": "low"}
    ideal = capture_room("ac-room", tmp_path / "ideal", ROOM)
    seeded = capture_room("ac-room", tmp_path / "seeded", dataclasses.replace(ROOM, noise_seed=3))
    assert _files(ideal.root) == _files(seeded.root)  # the seed does nothing at ideal
    meta = json.loads((ideal.root / "meta_data.json").read_text())
    assert list(meta["regnf"]["config"]) == SETTINGS_BEFORE_NOISE and "noise" not in meta["regnf"]
    assert not (ideal.root / TRUE_POSES_NAME).exists()

    noisy = capture_room("ac-room", tmp_path / "slam", dataclasses.replace(ROOM, noise="slam", noise_seed=1))
    assert noisy.meta["noise"]["level"] == "slam" and noisy.meta["config"]["noise"] == "slam"
    assert noisy.depth_noise == depth_noise_model(NOISE_LEVELS["slam"], float(noisy.frames[0].intrinsics[0][0]))
    true = np.array(json.loads((noisy.root / TRUE_POSES_NAME).read_text())["camtoworld_metres"])
    ideal_poses = np.stack([ideal.camtoworld_metres(i) for i in range(4)])
    stored = np.stack([noisy.camtoworld_metres(i) for i in range(4)])
    np.testing.assert_allclose(true, ideal_poses, atol=1e-12)  # rendered from the ideal poses
    pos, _ = _errors(stored, true)
    assert pos[-1] == pytest.approx(0.01, abs=4e-3)  # the drift, give or take the jitter
    hit = [(ideal.depth(i) > 0).mean() for i in range(4)]
    noisy_hit = [(noisy.depth(i) > 0).mean() for i in range(4)]
    assert all(b < a for a, b in zip(hit, noisy_hit))
    with pytest.raises(ValueError, match="noise must be one of"):
        capture_room("ac-room", tmp_path / "x", dataclasses.replace(ROOM, noise="loud"))
    assert not (tmp_path / "x").exists()
