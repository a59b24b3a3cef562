"""Samples of depth as sensors write it: flying pixels, confidence maps, per-sample sigma and
weights, the free-space margin, pixel stride and frame indices.

The scenes are depth images written by the test (a wall behind a box face with interpolated mixed
pixels at the step, a tilted plane), seen by one camera at the origin of a capture whose metres
are twice its normalised units, so the truth (which pixels are mixed, each pixel's z and
incidence, Nguyen et al.'s sigma) is known in closed form here.
"""

from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from regnf.captures.depth_uncertainty import DepthNoiseModel
from regnf.captures.model import Capture, CaptureError
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.observations.rgbd_samples import (
    MAX_INCIDENCE_DEG,
    build_samples,
    flying_pixels,
    free_depths,
    free_window_radius,
)
from regnf.training.training import _ViewStack, free_stop, hit_reach

W, H = 24, 16
F = 60.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
SCALE = 0.5
"""Metres per normalised unit of the test captures."""
WORLDTOGT = np.diag([SCALE, SCALE, SCALE, 1.0])
NEAR, FAR = 2.0, 3.0
"""Depth of the box face (columns < STEP) and of the wall behind it, metres."""
STEP = 10
MIXED = (NEAR + (FAR - NEAR) / 3, NEAR + 2 * (FAR - NEAR) / 3)
"""Depth of the two mixed pixels at columns STEP and STEP + 1 (a sensor's interpolation)."""


def step_depth() -> np.ndarray:
    """(H, W) metres: the box face, two interpolated mixed columns, the wall."""
    depth = np.full((H, W), FAR)
    depth[:, :STEP] = NEAR
    depth[:, STEP], depth[:, STEP + 1] = MIXED
    return depth


def write(root: Path, depths: list[np.ndarray], meta: dict | None, poses: np.ndarray | None = None) -> Capture:
    n = len(depths)
    rgb = [np.full((H, W, 3), 40 * (i + 1), np.uint8) for i in range(n)]
    write_capture(root, rgb, depths, np.stack([np.eye(4)] * n) if poses is None else poses, K, WORLDTOGT, meta=meta)
    return load_capture(root)


def pixels_of(dirs: torch.Tensor) -> np.ndarray:
    """(n, 2) int (v, u) of the pixels whose rays (camera = world frame) are ``dirs`` (n, 3)."""
    d = dirs.double().numpy()
    u = F * d[:, 0] / d[:, 2] + K[0, 2]
    v = F * d[:, 1] / d[:, 2] + K[1, 2]
    return np.stack([np.floor(v), np.floor(u)], -1).astype(int)


def sample_pixels(s) -> np.ndarray:
    return pixels_of(s.points - s.origins)


# -- flying pixels --------------------------------------------------------------------------------
def test_interpolated_mixed_pixels_at_a_step_are_flying_and_both_sides_are_kept() -> None:
    z = step_depth() / SCALE
    got = flying_pixels(z, z > 0, K)
    expect = np.zeros((H, W), bool)
    expect[:, STEP : STEP + 2] = True
    np.testing.assert_array_equal(got, expect)
    # The same along v, and one mixed pixel alone.
    np.testing.assert_array_equal(flying_pixels(z.T.copy(), z.T > 0, K), expect.T)
    one = np.where(np.arange(W) < STEP, NEAR, FAR)[None].repeat(H, 0) / SCALE
    one[:, STEP] = (NEAR + FAR) / 2 / SCALE
    assert flying_pixels(one, one > 0, K)[:, STEP].all() and flying_pixels(one, one > 0, K).sum() == H
    # A neighbour without depth is never one of the two: no flying pixel beside a hole.
    holed = z.copy()
    holed[:, STEP + 2] = 0.0
    assert not flying_pixels(holed, holed > 0, K)[:, STEP + 1].any()


def test_a_plane_seen_below_the_maximum_incidence_has_no_flying_pixel() -> None:
    for deg in (0.0, 45.0, 75.0):
        z = tilted_plane(deg)
        flying = flying_pixels(z, z > 0, K)
        # The view spans +-11 degrees: at 75 its right side sees the plane beyond 80.
        assert not flying[plane_incidence(deg) < math.radians(MAX_INCIDENCE_DEG - 2.0)].any(), deg
    assert flying.any()


def _rays() -> np.ndarray:
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    return np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], -1)


def _normal(deg: float) -> np.ndarray:
    th = math.radians(deg)
    return np.array([math.sin(th), 0.0, -math.cos(th)])


def tilted_plane(deg: float, z0: float = 2.5) -> np.ndarray:
    """(H, W) z-depth of a plane through (0, 0, z0) turned by ``deg`` about the camera's y axis."""
    return (_normal(deg) @ [0.0, 0.0, z0]) / (_rays() @ _normal(deg))


def plane_incidence(deg: float) -> np.ndarray:
    """(H, W) angle between each pixel's ray and the normal of :func:`tilted_plane`, radians."""
    rays = _rays()
    return np.arccos(np.abs(rays @ _normal(deg)) / np.linalg.norm(rays, axis=-1))


def test_a_noisy_capture_drops_flying_pixels_and_an_exact_one_keeps_them(tmp_path: Path) -> None:
    noisy = write(tmp_path / "n", [step_depth()], None)  # a user's capture: the default model
    exact = write(tmp_path / "e", [step_depth()], {"depth_noise": "none"})
    assert noisy.depth_noise == DepthNoiseModel() and exact.depth_noise is None
    cols_noisy = sample_pixels(build_samples(noisy, [0]))[:, 1]
    cols_exact = sample_pixels(build_samples(exact, [0]))[:, 1]
    assert sorted(set(cols_exact)) == list(range(W))
    assert sorted(set(cols_noisy)) == [c for c in range(W) if c not in (STEP, STEP + 1)]
    assert len(cols_noisy) == H * (W - 2)  # every clean pixel on both sides is kept
    # Nor does the view stack see free space in front of a flying pixel.
    views = _ViewStack.build(noisy, [0], torch.device("cpu"))
    assert torch.isnan(views.depth[0, :, STEP : STEP + 2]).all()
    assert torch.isfinite(views.depth[0, :, : STEP]).all() and torch.isfinite(views.depth[0, :, STEP + 2 :]).all()


def test_surfaces_beyond_the_maximum_incidence_are_dropped(tmp_path: Path) -> None:
    deg = 73.0  # incidence 62-84 degrees across the view
    cap = write(tmp_path, [tilted_plane(deg)], None)
    px = sample_pixels(build_samples(cap, [0]))
    kept = np.zeros((H, W), bool)
    kept[px[:, 0], px[:, 1]] = True
    theta = np.degrees(plane_incidence(deg))
    interior = np.zeros((H, W), bool)
    interior[1:-1, 1:-1] = True  # the border's normals are not trusted: theta 0 there
    assert (theta[interior] > MAX_INCIDENCE_DEG + 0.5).any() and (theta[interior] < MAX_INCIDENCE_DEG - 0.5).any()
    assert not kept[interior & (theta > MAX_INCIDENCE_DEG + 0.5)].any()
    assert kept[interior & (theta < MAX_INCIDENCE_DEG - 0.5)].all()


# -- confidence --------------------------------------------------------------------------------
def with_confidence(capture: Capture, conf: np.ndarray) -> Capture:
    path = capture.root / "confidence.png"
    iio.imwrite(path, conf)
    capture.frames[0].confidence_path = path
    return capture


def test_confidence_0_is_unknown_even_where_zeros_are_empty(tmp_path: Path) -> None:
    depth = np.full((H, W), FAR)
    depth[:, -4:] = 0.0  # no return: empty in this (ideal) capture
    conf = np.full((H, W), 2, np.uint8)
    conf[2:6, 2:6] = 0
    cap = with_confidence(write(tmp_path, [depth], {"zero_depth": "empty"}), conf)
    assert cap.depth_noise is None
    s = build_samples(cap, [0])
    px = sample_pixels(s)
    assert len(px) == H * (W - 4) - 16 and not (conf[px[:, 0], px[:, 1]] == 0).any()
    # Free rays only where the depth is 0, none on the low-confidence pixels.
    free = pixels_of(s.free_dirs)
    assert len(free) == H * 4 and (free[:, 1] >= W - 4).all()
    assert not (conf[pixels_of(s.edge_dirs)[:, 0], pixels_of(s.edge_dirs)[:, 1]] == 0).any()
    # Exact depth: no weights from the confidence either.
    assert bool((s.weights == 1).all()) and bool((s.sigma == 0).all())
    views = _ViewStack.build(cap, [0], torch.device("cpu"))
    assert torch.isnan(views.depth[0, 2:6, 2:6]).all() and (views.depth[0, :, -4:] == 0).all()


def test_medium_confidence_halves_the_weight(tmp_path: Path) -> None:
    conf = np.full((H, W), 2, np.uint8)
    conf[:, ::2] = 1
    cap = with_confidence(write(tmp_path, [np.full((H, W), 2.0)], None), conf)
    s = build_samples(cap, [0])
    px = sample_pixels(s)
    w = np.zeros((H, W))
    w[px[:, 0], px[:, 1]] = s.weights.double().numpy()
    # Neighbours at the same depth and nearly the same incidence: the medium one weighs half.
    np.testing.assert_allclose(w[4:-4, 4:-4:2] / w[4:-4, 5:-3:2], 0.5, rtol=1e-3)


def test_a_bad_confidence_file_is_refused_naming_it(tmp_path: Path) -> None:
    cap = with_confidence(write(tmp_path, [step_depth()], None), np.zeros((H + 1, W), np.uint8))
    with pytest.raises(CaptureError, match=r"confidence.png: frame 0: depth confidence shape \(17, 24\) does not match the depth's 16x24"):
        build_samples(cap, [0])


# -- sigma and weights -------------------------------------------------------------------------
def nguyen(z: np.ndarray, theta: np.ndarray) -> np.ndarray:
    return 0.0012 + 0.0019 * (z - 0.4) ** 2 + 0.0001 / np.sqrt(z) * theta**2 / (np.pi / 2 - theta) ** 2


def test_sigma_and_weights_follow_depth_and_incidence(tmp_path: Path) -> None:
    deg = 50.0
    z = tilted_plane(deg, z0=1.6)  # metres: written as is, normalised = metres / SCALE
    cap = write(tmp_path, [z], None)
    s = build_samples(cap, [0])
    px = sample_pixels(s)
    z_px = z[px[:, 0], px[:, 1]]
    theta = plane_incidence(deg)[px[:, 0], px[:, 1]]  # closed form
    border = (px[:, 0] == 0) | (px[:, 0] == H - 1) | (px[:, 1] == 0) | (px[:, 1] == W - 1)
    sigma_m = s.sigma.double().numpy() * SCALE
    np.testing.assert_allclose(sigma_m[~border], nguyen(z_px, theta)[~border], rtol=1e-4)
    # No trusted normal on the border: theta 0 there.
    np.testing.assert_allclose(sigma_m[border], nguyen(z_px, 0.0 * theta)[border], rtol=1e-5)
    want = np.clip((0.002 / nguyen(z_px, np.where(border, 0.0, theta))) ** 2, 0.1, 1.0)
    np.testing.assert_allclose(s.weights.double().numpy(), want, rtol=1e-4)
    assert ((want > 0.1) & (want < 1.0)).mean() > 0.9  # mostly between the clips: the test sees the formula
    # Farther is noisier: the same plane twice as far weighs less everywhere.
    s_far = build_samples(write(tmp_path / "far", [2.0 * z], None), [0])
    assert s_far.points.shape == s.points.shape and (s_far.sigma > s.sigma).all()
    assert (s_far.weights <= s.weights).all() and (s_far.weights < s.weights)[s.weights > 0.1].all()


def test_ideal_depth_has_unit_weights_and_no_sigma(tmp_path: Path) -> None:
    cap = write(tmp_path, [step_depth()], {"generator": "regnf.synthetic/2"})
    s = build_samples(cap, [0])
    assert cap.depth_noise is None and s.points.shape[0] == H * W  # nothing dropped
    assert s.weights.dtype == torch.float32 and bool((s.weights == 1).all()) and bool((s.sigma == 0).all())
    views = _ViewStack.build(cap, [0], torch.device("cpu"))
    assert torch.equal(views.depth[0], torch.from_numpy(cap.depth(0)))


# -- free-space margin -------------------------------------------------------------------------
def test_free_space_stops_before_the_depth_by_the_larger_of_margin_and_k_sigma() -> None:
    t = torch.tensor([2.0, 2.0, 5.0])
    sigma = torch.tensor([0.001, 0.05, 0.2])
    torch.testing.assert_close(free_stop(t, sigma, 0.02, 3.0), torch.tensor([1.98, 1.85, 4.4]))
    assert torch.equal(free_stop(t, None, 0.02, 3.0), t - 0.02)


def test_the_true_surface_is_within_the_hit_bound_of_noisy_depth() -> None:
    """Rays at normal incidence to a plane at D, depths D + N(0, sigma): the true SDF, D - t,
    breaks the bound S <= reach - t on almost no ray with the noise-aware reach, and on half of
    them (by 0.8 sigma on average) were the bound at the noisy depth itself."""
    D, sigma = 3.0, 0.02
    gen = torch.Generator().manual_seed(0)
    depth = D + sigma * torch.randn(100_000, generator=gen, dtype=torch.float64)
    t = depth - 0.5 * torch.rand(depth.shape[0], generator=gen, dtype=torch.float64)
    true_sdf = D - t

    def excess(reach: torch.Tensor) -> torch.Tensor:
        return torch.relu(true_sdf - (reach - t))

    noisy = excess(hit_reach(depth, torch.full_like(depth, sigma), 3.0))
    assert float((noisy > 0).double().mean()) < 0.01 and float(noisy.mean()) < 1e-3 * sigma
    at_depth = excess(depth)
    assert abs(float((at_depth > 0).double().mean()) - 0.5) < 0.01
    assert abs(float(at_depth.mean()) - sigma / (2 * torch.pi) ** 0.5) < 0.02 * sigma
    assert torch.equal(hit_reach(depth, None, 3.0), depth)  # exact depth: the depth itself


def test_the_view_stack_margin_grows_with_the_depths_sigma(tmp_path: Path) -> None:
    wall_m = 4.0  # sigma 2.58 cm at normal incidence: 3 sigma = 7.7 cm > the 2 cm margin
    noisy = write(tmp_path / "n", [np.full((H, W), wall_m)], None)
    exact = write(tmp_path / "e", [np.full((H, W), wall_m)], {"depth_noise": "none"})
    margin = 0.02 / SCALE
    k_sigma = 3.0 * nguyen(np.array(wall_m), np.array(0.0)) / SCALE
    gaps = np.array([0.01, 0.05, 0.1]) / SCALE  # before the wall, along the optical axis
    x = torch.tensor([[0.0, 0.0, wall_m / SCALE - g] for g in gaps], dtype=torch.float32)
    view = torch.zeros(len(gaps), dtype=torch.long)
    assert margin < gaps[1] < k_sigma < gaps[2]
    got_exact = _ViewStack.build(exact, [0], torch.device("cpu")).seen_free(x, margin, view)
    got_noisy = _ViewStack.build(noisy, [0], torch.device("cpu")).seen_free(x, margin, view)
    assert got_exact.tolist() == [0.0, 1.0, 1.0]
    assert got_noisy.tolist() == [0.0, 0.0, 1.0]


# -- stride and frames -------------------------------------------------------------------------
def busy_capture(root: Path) -> Capture:
    """A capture with every kind of sample: a step with flying pixels, a hole of empty zeros,
    low- and medium-confidence pixels, two frames."""
    depth = step_depth()
    depth[3:7, 15:19] = 0.0
    conf = np.full((H, W), 2, np.uint8)
    conf[10:13, 2:5] = 0
    conf[8:, 16:] = 1
    pose = np.eye(4)
    pose[:3, 3] = [0.05, -0.02, 0.0]
    cap = write(root, [depth, np.flip(depth, 1).copy()], {"zero_depth": "empty", "depth_noise": {}},
                np.stack([np.eye(4), pose]))
    return with_confidence(cap, conf)


FIELDS = ("points", "colors", "normals", "normal_ok", "origins", "ray_t", "outline", "weights", "sigma", "frame")


def test_pixel_stride_2_gives_the_stride_1_samples_at_the_kept_pixels(tmp_path: Path) -> None:
    cap = busy_capture(tmp_path)
    indices = [1, 0]
    one, two = build_samples(cap, indices), build_samples(cap, indices, pixel_stride=2)
    assert one.free_dirs.shape[0] > 0 and one.edge_t.shape[0] > 0 and not bool((one.weights == 1).all())

    def kept(dirs: torch.Tensor, origins: torch.Tensor) -> torch.Tensor:
        # Each frame's camera is translated only: its pixel follows from the ray's direction.
        px = pixels_of(dirs)
        return torch.from_numpy((px[:, 0] % 2 == 0) & (px[:, 1] % 2 == 0))

    keep = kept(one.points - one.origins, one.origins)
    assert 0 < int(keep.sum()) == two.points.shape[0] < one.points.shape[0]
    for name in FIELDS:
        assert torch.equal(getattr(one, name)[keep], getattr(two, name)), name
    keep_free = kept(one.free_dirs, one.free_origins)
    for name in ("free_origins", "free_dirs", "free_frame"):
        assert torch.equal(getattr(one, name)[keep_free], getattr(two, name)), name
    keep_edge = kept(one.edge_dirs, one.edge_origins)
    for name in ("edge_origins", "edge_dirs", "edge_t", "edge_limit", "edge_frame"):
        assert torch.equal(getattr(one, name)[keep_edge], getattr(two, name)), name
    with pytest.raises(ValueError, match="pixel_stride must be an integer >= 1, got 0"):
        build_samples(cap, indices, pixel_stride=0)


def test_each_sample_knows_its_frame(tmp_path: Path) -> None:
    cap = busy_capture(tmp_path)
    s = build_samples(cap, [1, 0])
    centres = {0: np.zeros(3), 1: np.array([0.05, -0.02, 0.0]) / SCALE}
    for frame, origins in ((s.frame, s.origins), (s.free_frame, s.free_origins), (s.edge_frame, s.edge_origins)):
        assert frame.dtype == torch.int32 and frame.shape[0] == origins.shape[0]
        assert set(frame.tolist()) == {0, 1}
        for j, i in enumerate([1, 0]):  # index j into indices is frame i
            np.testing.assert_allclose(origins[frame == j].double().numpy(), centres[i][None].repeat(int((frame == j).sum()), 0), atol=1e-6)


def test_a_capture_with_a_noise_model_gets_its_own_cache_key(tmp_path: Path) -> None:
    from regnf.synthetic.cache import Cache
    from regnf.training.presets import object_rgbd_preset

    cache, cfg = Cache(tmp_path / "cache"), object_rgbd_preset()
    noisy = write(tmp_path / "n", [step_depth()], None)
    key_noisy = cache.rgbd_entry(noisy, cfg)[0].name
    # The same bytes read with another model: another key.
    noisy.meta["depth_noise"] = {"constant_m": 0.004}
    assert cache.rgbd_entry(noisy, cfg)[0].name != key_noisy
    noisy.meta["depth_noise"] = "none"
    key_exact = cache.rgbd_entry(noisy, cfg)[0].name
    assert key_exact != key_noisy
    # A confidence map is training data: its bytes are in the key.
    with_confidence(noisy, np.full((H, W), 2, np.uint8))
    key_conf = cache.rgbd_entry(noisy, cfg)[0].name
    assert key_conf != key_exact
    iio.imwrite(noisy.frames[0].confidence_path, np.full((H, W), 1, np.uint8))
    assert cache.rgbd_entry(noisy, cfg)[0].name not in (key_conf, key_exact)


def test_a_capture_with_a_noise_model_trains(tmp_path: Path) -> None:
    from regnf.fields.neural_sdf import NeuralSDFConfig
    from regnf.training.training import RGBDTrainConfig, train_rgbd

    poses = np.stack([np.eye(4)] * 2)
    poses[:, :3, 3] = [[0.0, 0.0, -2.5], [0.05, -0.02, -2.5]]  # the scene inside the capture's box
    cap = write(tmp_path, [step_depth(), np.flip(step_depth(), 1).copy()], None, poses)
    tiny = NeuralSDFConfig(levels=2, features_per_level=2, base_resolution=8, finest_resolution=16,
                           hidden_dim=16, color_hidden_dim=16)
    cfg = RGBDTrainConfig(steps=3, batch_surface=64, batch_free=32, batch_empty=32, batch_eikonal=32,
                          w_edge=1.0, batch_edge=32, visibility_resolution=0, architecture=tiny)
    _, log = train_rgbd(cap, cfg, progress=False)
    assert len(log.losses) > 0 and all(math.isfinite(v) for v in log.losses[-1].values())


# -- lateral noise at outlines ---------------------------------------------------------------
def test_a_rays_free_space_ends_at_the_nearest_depth_around_it(tmp_path: Path) -> None:
    """A pixel of the box face that read the wall behind (lateral noise at the outline) is free
    only up to the box face its neighbours saw; everywhere else up to its own depth."""
    depth = step_depth()
    depth[:, STEP : STEP + 2] = FAR  # no mixed pixels: a clean step
    jittered = (5, STEP - 1)
    depth[jittered] = FAR
    z = depth / SCALE
    expect = z.copy()
    expect[:, STEP : STEP + 1] = NEAR / SCALE  # the wall's first column is beside the face
    expect[4:7, STEP - 2 : STEP + 1] = NEAR / SCALE
    np.testing.assert_array_equal(free_depths(z, z > 0, 1), expect)
    cap = write(tmp_path, [depth], None)
    s = build_samples(cap, [0])
    px = sample_pixels(s)
    ray_len = (s.ray_t / torch.from_numpy(z[px[:, 0], px[:, 1]]).float()).double().numpy()
    want = expect[px[:, 0], px[:, 1]] * ray_len
    np.testing.assert_allclose(s.ray_free_t.double().numpy(), want, rtol=1e-6)
    # The views' free-space test agrees: a point just in front of the wall along the jittered
    # pixel's ray (inside the box face's extension) is not seen free.
    views = _ViewStack.build(cap, [0], torch.device("cpu"))
    ray = np.array([(jittered[1] + 0.5 - K[0, 2]) / F, (jittered[0] + 0.5 - K[1, 2]) / F, 1.0])
    x = torch.tensor([ray * (FAR - 0.2) / SCALE, ray * (NEAR - 0.2) / SCALE], dtype=torch.float32)
    got = views.seen_free(x, 0.02 / SCALE, torch.zeros(2, dtype=torch.long))
    assert got.tolist() == [0.0, 1.0]
    # Exact depth keeps each ray's own depth.
    exact = build_samples(write(tmp_path / "e", [depth], {"depth_noise": "none"}), [0])
    assert exact.ray_free_t is None


@pytest.mark.parametrize("lateral_px", [0.0, 0.1, 0.15, 0.3, 0.5, 0.8, 1.6])
def test_the_free_window_holds_every_neighbour_a_jittered_read_reaches(lateral_px: float) -> None:
    """A pixel's depth, read at its centre jittered by a Gaussian of ``lateral_px``, lands in a
    pixel beyond the window (more than ``radius + 1/2`` pixels away) at most as often as a
    Gaussian exceeds two sigma; a window one pixel smaller would miss it more often."""
    rng = np.random.default_rng(0)
    read = lateral_px * rng.standard_normal(400_000)
    radius = free_window_radius(lateral_px)
    beyond_two_sigma = 2 * (1 - 0.97725)  # P(|N(0, 1)| > 2)
    assert np.mean(np.abs(np.round(read)) > radius) <= beyond_two_sigma
    if radius > 0:
        assert np.mean(np.abs(np.round(read)) > radius - 1) > beyond_two_sigma


def test_a_sensor_whose_reads_stay_within_their_pixel_keeps_each_rays_own_free_space(tmp_path: Path) -> None:
    """With a lateral sigma of a sixth of a pixel (a Kinect's depth read at a third of its
    resolution) the ray beside the box face is free up to the wall it saw, and the occluding-edge
    samples on it reach past the face's depth; at ICL-NUIM's half a pixel they have no room."""
    depth = step_depth()
    depth[:, STEP : STEP + 2] = FAR  # a clean step

    def z_of(t: torch.Tensor, dirs: torch.Tensor) -> np.ndarray:
        d = dirs.double().numpy()  # camera = world frame: z-depth = distance x d_z / |d|
        return t.double().numpy() * d[:, 2] / np.linalg.norm(d, axis=-1)

    fine, coarse = (build_samples(write(tmp_path / str(sigma), [depth], {"depth_noise": {"lateral_px": sigma}}), [0])
                    for sigma in (1 / 6, 0.5))
    for s in (fine, coarse):
        assert s.edge_t.shape[0] == H  # one edge ray per row: the wall's first column
        np.testing.assert_allclose(z_of(s.edge_t, s.edge_dirs), NEAR / SCALE, rtol=1e-5)
    margin = 0.02 / SCALE
    np.testing.assert_allclose(z_of(fine.edge_limit, fine.edge_dirs), FAR / SCALE, rtol=1e-5)
    assert (coarse.edge_limit - margin <= coarse.edge_t).all()
    beside = torch.from_numpy(sample_pixels(fine)[:, 1] == STEP)
    assert int(beside.sum()) == H
    np.testing.assert_allclose(z_of(fine.ray_free_t[beside], fine.points[beside] - fine.origins[beside]),
                               FAR / SCALE, rtol=1e-5)
