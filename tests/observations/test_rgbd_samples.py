"""RGB-D sample building against a sphere-traced capture of an analytic object and closed forms."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from regnf.captures.model import Capture
from regnf.observations.rgbd_samples import (
    backproject_frame,
    build_samples,
    edge_depths,
    outline_pixels,
    ray_box_interval,
)

from .capture_helpers import (
    BOX_CENTER,
    BOX_COLOR,
    BOX_HALF,
    FOCAL,
    HEIGHT,
    SPHERE_CENTER,
    SPHERE_COLOR,
    SPHERE_RADIUS,
    WIDTH,
    analytic_sdf,
    camera_poses,
    pixel_dirs_camera,
    write_analytic_capture,
)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Capture:
    return write_analytic_capture(Path(tmp_path_factory.mktemp("analytic_capture")))


# -- back-projection ----------------------------------------------------------------------------
def test_backprojected_depth_points_lie_on_the_analytic_surface(capture: Capture) -> None:
    idx = list(range(len(capture.frames)))
    s = build_samples(capture, idx)
    depths = [capture.depth(i) for i in idx]
    n_valid = sum(int((d > 0).sum()) for d in depths)
    assert s.points.shape == (n_valid, 3)
    assert n_valid > 0.15 * len(idx) * WIDTH * HEIGHT  # the object fills ~1/3 of the views
    # The capture was written in metres and loaded back in the normalised frame: the points
    # are on the normalised-frame surface (a wrong depth or pose scale would be far off).
    sdf = analytic_sdf(s.points.double().numpy())
    assert np.abs(sdf).max() < 1e-3
    # Origins are the camera centres (the poses rendered in the normalised frame), frame by frame.
    counts = [int((d > 0).sum()) for d in depths]
    centres = np.concatenate(
        [np.broadcast_to(p[:3, 3], (k, 3)) for p, k in zip(camera_poses(), counts)]
    )
    np.testing.assert_allclose(s.origins.numpy(), centres, atol=1e-5)
    # Each point is ray_t along a unit ray from its camera's centre.
    dist = np.linalg.norm(s.points.double().numpy() - s.origins.double().numpy(), axis=1)
    np.testing.assert_allclose(s.ray_t.double().numpy(), dist, rtol=1e-5)


def test_sample_colours_are_the_analytic_colours(capture: Capture) -> None:
    s = build_samples(capture, capture.train_indices())
    p = s.points.double().numpy()
    on_sphere = (np.linalg.norm(p - SPHERE_CENTER, axis=1) - SPHERE_RADIUS) < analytic_sdf(p) + 1e-6
    want = np.where(on_sphere[:, None], np.array(SPHERE_COLOR), np.array(BOX_COLOR))
    err = np.abs(s.colors.double().numpy() - want).max(axis=1)
    # uint8 PNG quantisation: half a level; the winner of the union may flip on the seam only.
    assert (err <= 0.5 / 255 + 1e-6).mean() > 0.999
    assert ((s.colors >= 0) & (s.colors <= 1)).all()


def test_backproject_frame_matches_a_closed_form_plane() -> None:
    K = np.array([[20.0, 0.0, 8.0], [0.0, 22.0, 6.5], [0.0, 0.0, 1.0]])
    h, w = 12, 16
    R = Rotation.from_euler("xyz", [20.0, -35.0, 110.0], degrees=True).as_matrix()
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, [0.3, -1.2, 2.0]
    # Plane n . X = d in the camera frame; its z-depth along ray r (r_z = 1) is d / (n . r).
    n_cam = np.array([0.3, -0.5, -1.0]) / np.linalg.norm([0.3, -0.5, -1.0])
    d = float(n_cam @ np.array([0.0, 0.0, 3.0]))  # the plane passes through (0, 0, 3)
    r = pixel_dirs_camera(K, h, w)
    depth = d / (r @ n_cam)
    assert (depth > 0).all()
    depth[2, 3] = 0.0  # no hit
    depth[5, 7] = np.nan  # sensor dropout
    points, dirs, valid = backproject_frame(depth, K, c2w)
    expect_valid = np.ones((h, w), bool)
    expect_valid[2, 3] = expect_valid[5, 7] = False
    np.testing.assert_array_equal(valid, expect_valid)
    # World points are the camera-frame points z * r moved by the pose.
    cam_pts = np.nan_to_num(depth)[..., None] * r
    np.testing.assert_allclose(points[valid], (cam_pts @ R.T + c2w[:3, 3])[valid], atol=1e-12)
    n_world, d_world = R @ n_cam, d + (R @ n_cam) @ c2w[:3, 3]
    np.testing.assert_allclose(points[valid] @ n_world, d_world, atol=1e-12)
    # Unit directions through the pixel centres, rotated into the world, for every pixel.
    r_world = r @ R.T
    np.testing.assert_allclose(
        dirs, r_world / np.linalg.norm(r_world, axis=-1, keepdims=True), atol=1e-12
    )
    assert np.isfinite(points).all()


# -- free rays ----------------------------------------------------------------------------------
def _ray_misses_sphere(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    t = np.maximum(((c - o) * d).sum(-1), 0.0)
    return np.linalg.norm(o + t[:, None] * d - c, axis=-1) > r


def _ray_misses_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t_in = np.nanmax(np.minimum(ta, tb), axis=-1)
    t_out = np.nanmin(np.maximum(ta, tb), axis=-1)
    return (t_in > t_out) | (t_out < 0)


def test_pixels_without_depth_become_free_rays_that_miss_the_object(capture: Capture) -> None:
    idx = capture.train_indices()
    s = build_samples(capture, idx)
    empty = [int((capture.depth(i) <= 0).sum()) for i in idx]
    assert s.free_dirs.shape == (sum(empty), 3) and s.free_origins.shape == (sum(empty), 3)
    assert sum(empty) > 0.3 * len(idx) * WIDTH * HEIGHT
    np.testing.assert_allclose(s.free_dirs.norm(dim=-1).numpy(), 1.0, atol=1e-6)
    # Origins are the cameras' centres, in frame order.
    centres = np.concatenate(
        [np.broadcast_to(capture.frames[i].camtoworld[:3, 3], (k, 3)) for i, k in zip(idx, empty)]
    )
    np.testing.assert_allclose(s.free_origins.numpy(), centres, atol=1e-6)
    # Closed-form ray-solid tests: no free ray enters the object (shrunk by 1e-3 for grazing rays).
    o, d = s.free_origins.double().numpy(), s.free_dirs.double().numpy()
    eps = 1e-3
    miss_sphere = _ray_misses_sphere(o, d, SPHERE_CENTER, SPHERE_RADIUS - eps)
    miss_box = _ray_misses_box(o, d, BOX_CENTER - BOX_HALF + eps, BOX_CENTER + BOX_HALF - eps)
    assert (miss_sphere & miss_box).all()
    # ... while the rays of the object's pixels do hit it (the same tests are not vacuous).
    hit_dirs = (s.points - s.origins).double().numpy() / s.ray_t.double().numpy()[:, None]
    ho = s.origins.double().numpy()
    hit_any = ~_ray_misses_sphere(
        ho, hit_dirs, SPHERE_CENTER, SPHERE_RADIUS + eps
    ) | ~_ray_misses_box(ho, hit_dirs, BOX_CENTER - BOX_HALF - eps, BOX_CENTER + BOX_HALF + eps)
    assert hit_any.all()


def test_edge_depths_of_a_step_a_slant_and_a_hole() -> None:
    K = np.array([[100.0, 0.0, 5.0], [0.0, 100.0, 4.0], [0.0, 0.0, 1.0]])
    h, w = 8, 10
    # A background plane at 3 m, slanted gently along u (no edge), with a box at 1 m in front.
    depth = 3.0 + 0.01 * np.arange(w)[None, :].repeat(h, 0)
    depth[3:5, 4:6] = 1.0
    depth[0, 0] = 0.0  # no hit, beside the background
    valid = depth > 0
    z = edge_depths(depth, valid, K)
    expect = np.zeros((h, w))
    # The 4-neighbours of the box on the background see the box's depth; the box itself and
    # the slanted background (steps of 0.01 m, far under 8 footprints of 0.03 m) see no edge.
    for v, u in [(2, 4), (2, 5), (5, 4), (5, 5), (3, 3), (4, 3), (3, 6), (4, 6)]:
        expect[v, u] = 1.0
    # A pixel without depth is beside an edge: the nearest of its neighbours with depth.
    expect[0, 0] = min(depth[0, 1], depth[1, 0])
    np.testing.assert_allclose(z, expect)


def test_outline_pixels_of_a_step_a_slant_and_a_hole() -> None:
    K = np.array([[100.0, 0.0, 5.0], [0.0, 100.0, 4.0], [0.0, 0.0, 1.0]])
    h, w = 8, 10
    depth = 3.0 + 0.01 * np.arange(w)[None, :].repeat(h, 0)
    depth[3:5, 4:6] = 1.0
    depth[0, 0] = 0.0
    valid = depth > 0
    got = outline_pixels(depth, valid, K)
    expect = np.zeros((h, w), dtype=bool)
    # Every pixel of the 2 x 2 box has a farther neighbour; the slant's steps are no edge; the
    # two background pixels beside the hole have a neighbour with no depth; the image's border
    # is no outline (nothing is known beyond it), and a pixel without depth never is one.
    expect[3:5, 4:6] = True
    expect[0, 1] = expect[1, 0] = True
    np.testing.assert_array_equal(got, expect)


def test_outline_points_lie_on_the_analytic_surface_at_grazing_angles(capture: Capture) -> None:
    s = build_samples(capture, capture.train_indices())
    o = s.outline.numpy()
    assert o.dtype == bool and o.shape == (s.points.shape[0],)
    assert 100 < o.sum() < 0.2 * len(o)
    x = s.points.double().numpy()
    assert np.abs(analytic_sdf(x[o])).max() < 1e-3
    # The analytic normal there is far nearer perpendicular to the ray that saw the point than
    # elsewhere (the sphere turns away at its silhouette; a box face's edge may be seen head-on).
    eps = 1e-5
    grad = np.stack([(analytic_sdf(x + eps * e) - analytic_sdf(x - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
    rays = x - s.origins.double().numpy()
    cos = np.abs((grad * rays).sum(-1)) / (np.linalg.norm(grad, axis=-1) * np.linalg.norm(rays, axis=-1))
    assert np.median(cos[o]) < 0.6 * np.median(cos[~o])


def test_edge_rays_pass_just_outside_the_analytic_silhouette(capture: Capture) -> None:
    s = build_samples(capture, capture.train_indices())
    assert s.edge_t.shape[0] > 100
    x = (s.edge_origins + s.edge_t[:, None] * s.edge_dirs).double().numpy()
    sdf = analytic_sdf(x)
    # Every edge ray misses the occluder (it hit something farther, or nothing), so the point
    # at the occluder's depth is outside the object, and within about a pixel footprint of it.
    footprint = s.edge_t.double().numpy() / FOCAL
    assert (sdf > -1e-4).all()
    assert np.median(sdf / footprint) < 1.0
    assert np.percentile(sdf / footprint, 95) < 3.0
    # The ray's own hit (inf: none) lies beyond the edge.
    assert (s.edge_limit > s.edge_t).all()


def test_build_samples_of_a_frame_subset(capture: Capture) -> None:
    one = build_samples(capture, [3])
    two = build_samples(capture, [3, 5])
    d3, d5 = capture.depth(3), capture.depth(5)
    assert one.points.shape[0] == int((d3 > 0).sum())
    assert two.points.shape[0] == int((d3 > 0).sum() + (d5 > 0).sum())
    assert torch.equal(two.points[: one.points.shape[0]], one.points)
    assert two.normal_ok.dtype == torch.bool and two.normal_ok.shape == (two.points.shape[0],)


def test_build_samples_needs_depth(capture: Capture) -> None:
    capture.frames[2].depth_path, saved = None, capture.frames[2].depth_path
    try:
        with pytest.raises(ValueError, match="frame 2 .*no depth"):
            build_samples(capture, [1, 2])
    finally:
        capture.frames[2].depth_path = saved


# -- ray / box intervals ------------------------------------------------------------------------
UNIT_BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
S2 = math.sqrt(2.0)


@pytest.mark.parametrize(
    ("origin", "direction", "t_in", "t_out"),
    [
        ((-3.0, 0.0, 0.0), (1.0, 0.0, 0.0), 2.0, 4.0),  # straight through along +x
        ((0.0, 0.0, 5.0), (0.0, 0.0, -1.0), 4.0, 6.0),  # along -z
        ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.0, 1.0),  # from inside: entry clamped at 0
        ((-2.0, -2.0, 0.5), (1 / S2, 1 / S2, 0.0), S2, 3 * S2),  # diagonal, enters at a corner edge
        ((0.5, -0.25, -3.0), (0.0, 0.0, 1.0), 2.0, 4.0),  # two zero direction components
    ],
)
def test_ray_box_interval_hand_computed(origin, direction, t_in, t_out) -> None:
    o = torch.tensor([origin], dtype=torch.float64)
    d = torch.tensor([direction], dtype=torch.float64)
    a, b = ray_box_interval(o, d, UNIT_BOX.double())
    assert a.item() == pytest.approx(t_in, abs=1e-9)
    assert b.item() == pytest.approx(t_out, abs=1e-9)


@pytest.mark.parametrize(
    ("origin", "direction"),
    [
        ((-3.0, 2.5, 0.0), (1.0, 0.0, 0.0)),  # passes above the box
        ((3.0, 0.0, 0.0), (1.0, 0.0, 0.0)),  # box behind the origin
        ((2.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # parallel to the x slab, outside it
    ],
)
def test_ray_box_interval_misses_are_empty(origin, direction) -> None:
    o = torch.tensor([origin], dtype=torch.float64)
    d = torch.tensor([direction], dtype=torch.float64)
    a, b = ray_box_interval(o, d, UNIT_BOX.double())
    assert b.item() < a.item()


def test_ray_box_interval_anisotropic_box_batched() -> None:
    bounds = torch.tensor([[0.0, -1.0, 2.0], [4.0, 1.0, 3.0]])
    o = torch.tensor([[-1.0, 0.0, 2.5], [2.0, 0.0, 0.0], [2.0, 0.0, 2.5]])
    d = torch.nn.functional.normalize(
        torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [3.0, 0.0, 4.0]]), dim=-1
    )
    a, b = ray_box_interval(o, d, bounds)
    # Row 3 starts inside; it leaves through z = 3 after t = 0.5 / 0.8 (x would need 2 / 0.6).
    np.testing.assert_allclose(a.numpy(), [1.0, 2.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(b.numpy(), [5.0, 3.0, 0.625], atol=1e-6)
