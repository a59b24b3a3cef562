"""The sphere tracer against closed-form ray intersections, in metres."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from regnf.compositor import Camera, SphereTracerConfig, look_at, orbit_cameras, render
from regnf.fields.analytic import Box, Sphere, Union
from regnf.fields.distance_grid import DistanceGrid
from regnf.fields.field import Field
from regnf.fields.similarity import similarity_matrix
from regnf.render.sphere_tracer import trace

from . import helpers as H
from .test_composite_field import make_composite

W, HGT = 64, 48

# A sphere of radius 0.5 field units whose field frame is 2x smaller than metres, rotated
# and moved: in the world it has radius 1 m around WORLD_CENTER.
TO_WORLD = similarity_matrix(
    Rotation.from_euler("z", 20, degrees=True).as_matrix(), np.array([1.0, 2.0, 0.5]), 2.0
)
FIELD_CENTER = np.array([0.1, -0.2, 0.3])
WORLD_CENTER = TO_WORLD[:3, :3] @ FIELD_CENTER + TO_WORLD[:3, 3]
WORLD_RADIUS = 1.0


def world_sphere() -> Sphere:
    return Sphere(0.5, FIELD_CENTER, color=(0.2, 0.4, 0.9), to_world=TO_WORLD)


def sphere_camera() -> Camera:
    return Camera.from_fov(
        W, HGT, 50.0, look_at(WORLD_CENTER + np.array([4.0, 1.0, 1.5]), WORLD_CENTER)
    )


def boundary(miss: np.ndarray, t_scale: float, cam: Camera, pixels: float = 1.5) -> np.ndarray:
    """Pixels whose ray passes within ``pixels`` footprints of the silhouette."""
    return np.abs(miss) < pixels * t_scale / cam.K[0, 0]


def test_sphere_depth_mask_normals_in_metres() -> None:
    cam = sphere_camera()
    out = render(world_sphere(), cam)
    o, d = H.pixel_rays(cam.K, cam.camera_to_world, W, HGT)
    hit, t, miss = H.ray_sphere(o, d, WORLD_CENTER, WORLD_RADIUS)
    dist = float(np.linalg.norm(cam.center - WORLD_CENTER))
    edge = boundary(miss, dist, cam)
    mask = out.mask.numpy().ravel()
    assert hit.sum() > 300 and (~hit).sum() > 300
    assert np.array_equal(mask[~edge], hit[~edge])

    forward = cam.camera_to_world[:3, 2]
    both = hit & mask
    p = o + np.where(both, t, 0.0)[:, None] * d
    n_true = (p - WORLD_CENTER) / WORLD_RADIUS
    cos_inc = -np.einsum("ij,ij->i", n_true, d)
    frontal = both & (cos_inc > 0.2)  # the SDF tolerance costs tol / cos in depth
    depth = out.depth.numpy().ravel()
    np.testing.assert_allclose(depth[frontal], (t * (d @ forward))[frontal], atol=1e-4, rtol=0)
    normals = out.normals.numpy().reshape(-1, 3)
    assert float(np.einsum("ij,ij->i", normals[frontal], n_true[frontal]).min()) > 1 - 1e-6

    assert bool((out.depth[~out.mask] == 0).all())
    ids = out.instance_id.numpy().ravel()
    assert bool((ids[mask] == 0).all() and (ids[~mask] == -1).all())
    np.testing.assert_allclose(
        out.rgb.numpy().reshape(-1, 3)[mask], np.tile([0.2, 0.4, 0.9], (mask.sum(), 1)), atol=1e-6
    )
    # Evaluations are counted: a lone sphere costs a handful per hit pixel.
    evals = out.evals_per_pixel.numpy().ravel()
    assert float(np.median(evals[mask])) <= 10
    assert bool((evals >= 0).all()) and int(evals.sum()) > 0


def composite_camera() -> Camera:
    return Camera.from_fov(W, HGT, 70.0, look_at(np.array([1.2, -1.3, 1.0]), H.PLACED_CENTER))


def test_composite_instance_ids_and_depth() -> None:
    cam = composite_camera()
    out = render(make_composite(), cam)
    o, d = H.pixel_rays(cam.K, cam.camera_to_world, W, HGT)
    _, t_b, miss_b = H.ray_sphere(o, d, H.PLACED_CENTER, H.PLACED_RADIUS)
    t_f = H.ray_plane_z(o, d, 0.0)
    p_f = o + np.where(np.isfinite(t_f), t_f, 0.0)[:, None] * d
    on_floor = np.isfinite(t_f) & (np.abs(p_f[:, :2]) <= 2.0).all(axis=1)
    t_f = np.where(on_floor, t_f, np.inf)
    want = np.where(t_b < t_f, H.INSTANCE, np.where(on_floor, 0, -1))
    t_want = np.minimum(t_b, t_f)

    # Boundary pixels: near the ball's silhouette or the floor's far edge.
    edge_floor = np.isfinite(t_f) & (np.abs(np.abs(p_f[:, :2]) - 2.0) < 0.1).any(axis=1)
    edge = boundary(miss_b, 3.0, cam) | edge_floor
    ids = out.instance_id.numpy().ravel()
    assert {0, H.INSTANCE} <= set(want.tolist())
    assert np.array_equal(ids[~edge], want[~edge])
    depth = out.depth.numpy().ravel()
    forward = cam.camera_to_world[:3, 2]
    hit = (want >= 0) & ~edge
    cos_floor = -d[:, 2]
    ok = hit & ((want == H.INSTANCE) | (cos_floor > 0.2))
    ok &= ~((want == H.INSTANCE) & (np.abs(miss_b) < 0.05))  # grazing on the ball
    np.testing.assert_allclose(depth[ok], (t_want * (d @ forward))[ok], atol=1e-4, rtol=0)


def test_relaxed_steps_and_skipping_cut_evaluations_with_identical_depth() -> None:
    field, cam = make_composite(), composite_camera()
    fast = render(field, cam, SphereTracerConfig())
    plain = render(field, cam, SphereTracerConfig.plain())
    assert int((fast.mask != plain.mask).sum()) <= 2
    both = fast.mask & plain.mask
    assert float((fast.depth - plain.depth)[both].abs().max()) < 1e-4
    assert bool((fast.instance_id[both] == plain.instance_id[both]).all())
    e_fast, e_plain = int(fast.evals_per_pixel.sum()), int(plain.evals_per_pixel.sum())
    assert e_fast < 0.75 * e_plain, (e_fast, e_plain)
    assert int(fast.lookups_per_pixel.sum()) > 0 and int(plain.lookups_per_pixel.sum()) == 0
    # Each ingredient helps on its own too.
    no_grid = render(field, cam, SphereTracerConfig(grid_resolution=0))
    unrelaxed = render(field, cam, SphereTracerConfig(omega=1.0))
    assert int(no_grid.evals_per_pixel.sum()) < e_plain
    assert int(unrelaxed.evals_per_pixel.sum()) < e_plain


def test_prebuilt_grid_gives_the_same_image_and_bounds_distances() -> None:
    field, cam = make_composite(), composite_camera()
    grid = DistanceGrid.build(field, resolution=24)
    a = render(field, cam, SphereTracerConfig(grid_resolution=24), grid=grid)
    b = render(field, cam, SphereTracerConfig(grid_resolution=24))
    assert torch.equal(a.depth, b.depth) and torch.equal(a.evals_per_pixel, b.evals_per_pixel)
    # At most the scene and the object at each cell centre; culling leaves some out.
    assert 24**3 // 2 < grid.build_evals < 2 * 24**3
    # The look-up is a lower bound of the true distance to the surface (exact sphere).
    sph = Sphere(0.5, (0.1, 0.0, -0.2))
    g = DistanceGrid.build(sph, resolution=16)
    x = torch.rand(4000, 3) * (sph.bounds[1] - sph.bounds[0]) + sph.bounds[0]
    lb = g.lower_bound(x)
    true = sph.sdf(x)
    known = torch.isfinite(lb)
    assert int(known.sum()) > 100
    assert bool((lb[known] <= true[known] + 1e-6).all())


def view_dirs(cam: Camera) -> torch.Tensor:
    _, d = H.pixel_rays(cam.K, cam.camera_to_world, cam.width, cam.height)
    return torch.as_tensor(d, dtype=torch.float32).reshape(cam.height, cam.width, 3)


@pytest.mark.parametrize("refine", ["illinois", "bisection"])
def test_refinement_methods_agree(refine: str) -> None:
    cam = sphere_camera()
    ref = render(world_sphere(), cam, SphereTracerConfig.plain())
    out = render(world_sphere(), cam, SphereTracerConfig(refine=refine))
    assert int((ref.mask != out.mask).sum()) <= 2
    # Away from grazing incidence (where the SDF tolerance costs tol / cos in depth).
    both = (ref.mask & out.mask & (-(ref.normals * view_dirs(cam)).sum(-1) > 0.2)).numpy()
    assert both.sum() > 300
    assert float((ref.depth - out.depth).abs().numpy()[both].max()) < 1e-4


def test_tint_and_colours_in_the_image() -> None:
    tint = (0.5, 0.5, 1.0)
    out = render(make_composite(tint=tint), composite_camera())
    ball = out.instance_id == H.INSTANCE
    floor = out.instance_id == 0
    want_ball = torch.tensor(np.multiply(H.LIB_COLOR, tint), dtype=out.rgb.dtype)
    assert torch.allclose(out.rgb[ball], want_ball.expand(int(ball.sum()), 3), atol=1e-6)
    assert torch.allclose(
        out.rgb[floor],
        torch.tensor(H.FLOOR_COLOR, dtype=out.rgb.dtype).expand(int(floor.sum()), 3),
        atol=1e-6,
    )
    assert bool((out.rgb[~out.mask] == 0).all())  # default background is black


def test_camera_inside_an_object_is_refused() -> None:
    inside = Camera.from_fov(
        W, HGT, 60.0, look_at(H.PLACED_CENTER, H.PLACED_CENTER + [1.0, 0.0, 0.0])
    )
    with pytest.raises(ValueError, match="inside matter of instance 7"):
        render(make_composite(), inside)


class HalfNaN(Sphere):
    """A broken field: NaN on one side."""

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        s = super().sdf(x)
        return torch.where(x[:, 0] > 0.05, torch.full_like(s, math.nan), s)


def test_non_finite_field_values_are_an_error() -> None:
    field = HalfNaN(0.5)
    cam = Camera.from_fov(W, HGT, 50.0, look_at(np.array([0.0, -3.0, 0.5]), np.zeros(3)))
    with pytest.raises(ValueError, match="non-finite SDF"):
        render(field, cam, SphereTracerConfig(grid_resolution=0))
    with pytest.raises(ValueError, match="non-finite SDF"):
        render(field, cam)  # found while building the grid


class Empty(Field):
    """No surface anywhere in the bounds."""

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return torch.full((x.shape[0],), 0.75, dtype=x.dtype, device=x.device)

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        return torch.ones(x.shape[0], 3, dtype=x.dtype, device=x.device)


def test_empty_scene_renders_background() -> None:
    cam = Camera.from_fov(W, HGT, 50.0, look_at(np.array([0.0, -3.0, 0.5]), np.zeros(3)))
    cfg = SphereTracerConfig(background=(0.1, 0.2, 0.3))
    out = render(Empty(), cam, cfg)
    assert not bool(out.mask.any())
    assert bool((out.instance_id == -1).all()) and bool((out.depth == 0).all())
    assert torch.allclose(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand(HGT, W, 3))


def test_trace_validates_its_rays() -> None:
    field = Sphere(0.5)
    o = torch.tensor([[0.0, -2.0, 0.0]])
    with pytest.raises(ValueError, match="unit"):
        trace(field, o, torch.tensor([[0.0, 2.0, 0.0]]))
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        trace(field, o, torch.tensor([[0.0, 1.0]]))
    hits = trace(field, o, torch.tensor([[0.0, 1.0, 0.0]]))
    assert bool(hits.hit[0]) and float(hits.t[0]) == pytest.approx(1.5, abs=1e-5)
    assert int(hits.winner[0]) == 0 and int(hits.evals[0]) >= 1
    with pytest.raises(ValueError, match="omega"):
        SphereTracerConfig(omega=2.5)


def test_near_and_far_are_metres() -> None:
    cam = sphere_camera()
    dist = float(np.linalg.norm(cam.center - WORLD_CENTER))
    far_cut = render(world_sphere(), cam, SphereTracerConfig(far=dist - 1.5))
    assert not bool(far_cut.mask.any())
    assert bool(render(world_sphere(), cam, SphereTracerConfig(far=dist)).mask.any())


def test_cameras() -> None:
    cams = orbit_cameras(
        (0.0, 0.0, 0.5), radius=3.0, height=1.0, n=4, width=32, height_px=24, fov_deg=90.0
    )
    assert len(cams) == 4
    for cam in cams:
        c = cam.center
        assert np.hypot(c[0], c[1]) == pytest.approx(3.0) and c[2] == pytest.approx(1.5)
        fwd = cam.camera_to_world[:3, 2]
        to_target = np.array([0.0, 0.0, 0.5]) - c
        assert fwd @ to_target / np.linalg.norm(to_target) == pytest.approx(1.0)
        assert cam.camera_to_world[:3, 1] @ np.array([0.0, 0.0, 1.0]) < 0  # image y is down
        assert cam.K[0, 0] == pytest.approx(16.0) and cam.K[0, 2] == 16.0 and cam.K[1, 2] == 12.0
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 2), (0, 0, 0))
    with pytest.raises(ValueError, match="rigid"):
        Camera(np.eye(3), 4, 4, np.diag([2.0, 2.0, 2.0, 1.0]))


def test_relaxed_steps_do_not_skip_a_thin_sheet_in_front_of_a_body() -> None:
    # A 4 mm sheet 6 mm in front of a sphere: a relaxed step from the bounds' entry jumps
    # over the sheet into the sphere; Keinert's overlap test must send it back.
    field = Union(Box((0.002, 0.5, 0.5)), Sphere(0.4, (0.406, 0.0, 0.0)))
    yz = torch.stack(
        torch.meshgrid(torch.linspace(-0.2, 0.2, 9), torch.linspace(-0.2, 0.2, 9), indexing="ij"),
        -1,
    )
    o = torch.cat([torch.full((81, 1), -1.5), yz.reshape(-1, 2)], dim=1)
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(81, 3).contiguous()
    for cfg in (
        SphereTracerConfig(),
        SphereTracerConfig(grid_resolution=0),
        SphereTracerConfig.plain(),
    ):
        hits = trace(field, o, d, config=cfg)
        assert bool(hits.hit.all())
        np.testing.assert_allclose(hits.t.numpy(), 1.498, atol=1e-5)


def test_relaxed_step_over_a_thin_plate_is_not_taken_for_free_space() -> None:
    """Regression: a relaxed step that jumps over a thin table top must be verified before the
    distance grid may skip on from its landing point (the grid bound there says nothing about
    the segment behind it). The default tracer sees every pixel the textbook one sees."""
    floor = Box((1.5, 1.5, 0.05), (0.0, 0.0, -0.05), color=(0.5, 0.5, 0.5))
    top = Box((0.45, 0.3, 0.0125), (0.3, 0.2, 0.45), color=(0.8, 0.5, 0.2))
    leg = Box((0.02, 0.02, 0.22), (0.0, 0.0, 0.22), color=(0.8, 0.5, 0.2))
    field = Union(floor, top, leg)
    cam = Camera.from_fov(96, 72, 62.0, look_at((1.3, -1.25, 1.06), (0.0, 0.0, 0.22)))
    fast = render(field, cam, SphereTracerConfig())
    plain = render(field, cam, SphereTracerConfig.plain())
    assert int((fast.mask != plain.mask).sum()) == 0
    assert int((fast.instance_id != plain.instance_id).sum()) == 0
    assert float((fast.depth - plain.depth).abs().max()) < 1e-3


@pytest.mark.cuda
def test_sphere_on_the_device_matches_the_closed_form(device: str) -> None:
    """The tracer on ``--device``: the closed-form mask and depth, and the images on that device."""
    cam = sphere_camera()
    out = render(world_sphere().to(device), cam)
    assert out.depth.device.type == torch.device(device).type
    o, d = H.pixel_rays(cam.K, cam.camera_to_world, W, HGT)
    hit, t, miss = H.ray_sphere(o, d, WORLD_CENTER, WORLD_RADIUS)
    edge = boundary(miss, float(np.linalg.norm(cam.center - WORLD_CENTER)), cam)
    mask = out.mask.cpu().numpy().ravel()
    assert hit.sum() > 300 and np.array_equal(mask[~edge], hit[~edge])
    p = o + np.where(hit & mask, t, 0.0)[:, None] * d
    frontal = hit & mask & (-np.einsum("ij,ij->i", (p - WORLD_CENTER) / WORLD_RADIUS, d) > 0.2)
    depth = out.depth.cpu().numpy().ravel()
    np.testing.assert_allclose(depth[frontal], (t * (d @ cam.camera_to_world[:3, 2]))[frontal], atol=1e-4, rtol=0)
