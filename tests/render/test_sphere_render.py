"""Views by sphere tracing: :func:`render_many` is :func:`render` of each camera, depth is
z-depth, a sphere's area is the closed form's, and the cones that start the rays never pass a
surface."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from regnf.core.cameras import pinhole_rays
from regnf.fields.analytic import Box, Sphere, Union
from regnf.render.camera import Camera
from regnf.render.sphere_render import cone_starts, pixel_tiles, render, render_many
from regnf.render.sphere_tracer import SphereTracerConfig, trace

from .test_sphere_tracer import CONFIGS, CPU, intrinsics, look_at, ray_box, ray_sphere


def test_render_many_is_render_of_each_camera() -> None:
    # Two cameras of other sizes and focal lengths: each ray keeps its own pixel's footprint
    # tolerance (5 % of 1/20 and of 1/90 rad a unit of t, far above the absolute 1e-5).
    field = Sphere(0.5, (0.0, 0.0, 0.0), color=(0.9, 0.4, 0.2))
    cams = [Camera(intrinsics(20.0, 24, 16), 24, 16, look_at(np.array([0.0, -2.5, 0.3]), np.zeros(3))),
            Camera(intrinsics(90.0, 40, 30), 40, 30, look_at(np.array([1.8, 1.2, 0.9]), np.zeros(3)))]
    cfg = SphereTracerConfig(footprint_fraction=0.05, chunk=300)
    many = render_many(field, cams, cfg)
    assert len(many) == 2
    for cam, got in zip(cams, many, strict=True):
        alone = render(field, cam, cfg)
        assert got.rgb.shape == (cam.height, cam.width, 3)
        for a, b in zip(alone, got, strict=True):
            assert torch.equal(a, b)
    assert render_many(field, [], cfg) == []
    with pytest.raises(ValueError, match="pixel_angle"):
        trace(field, torch.zeros(4, 3) - 2.0, torch.tensor([[0.0, 0.0, 1.0]] * 4), cfg,
              pixel_angle=torch.ones(3))


def test_render_depth_is_z_depth() -> None:
    # A wide slab facing the camera: z-depth is constant although t is not.
    field = Box((5.0, 5.0, 0.25), (0.0, 0.0, 0.0), color=(0.2, 0.6, 1.0))
    C = np.eye(4)
    C[2, 3] = -3.0  # camera looks along +Z at the face z = -0.25
    out = render(field, Camera(intrinsics(40.0, 48, 32), 48, 32, C), SphereTracerConfig())
    assert bool(out.mask.all())
    np.testing.assert_allclose(out.depth.numpy(), 2.75, atol=1e-4)
    np.testing.assert_allclose(
        out.rgb.numpy(), np.broadcast_to([0.2, 0.6, 1.0], (32, 48, 3)), atol=1e-6
    )
    np.testing.assert_allclose(
        out.normals.numpy(), np.broadcast_to([0, 0, -1.0], (32, 48, 3)), atol=1e-5
    )
    assert bool((out.instance_id == 0).all())


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_render_sphere_area(config: SphereTracerConfig) -> None:
    D, r, f, n = 3.0, 0.5, 200.0, 128
    field = Sphere(r, (0.0, 0.0, 0.0), color=(1.0, 1.0, 1.0)).to(CPU)
    C = look_at(np.array([0.0, -D, 0.0]), np.zeros(3))
    out = render(field, Camera(intrinsics(f, n, n), n, n, C), config)
    assert out.rgb.shape == (n, n, 3) and out.depth.shape == (n, n)
    assert out.mask.shape == (n, n) and out.mask.dtype == torch.bool
    assert out.normals.shape == (n, n, 3)
    assert out.rgb.device == CPU
    # The silhouette is a cone of half angle asin(r / D): a disc of radius f tan(angle).
    area = math.pi * f**2 * r**2 / (D**2 - r**2)
    assert abs(float(out.mask.sum()) - area) / area < 0.02
    assert abs(float(out.rgb[..., 0].sum()) - area) / area < 0.02
    # Pixel (64, 64) spans [64, 65]^2, half a pixel off the optical axis (cx = 64): its
    # depth is D - r to second order and its normal tilts by about 0.5 px / f * D / r.
    c = n // 2
    assert abs(float(out.depth[c, c]) - (D - r)) < 1e-3
    np.testing.assert_allclose(out.normals[c, c].numpy(), [0.0, -1.0, 0.0], atol=0.02)
    assert float(out.depth[0, 0]) == 0.0 and not bool(out.mask[0, 0])
    assert int(out.instance_id[0, 0]) == -1


def plate_before_wall(back_wall: bool = False) -> tuple[Union, list[tuple[np.ndarray, np.ndarray]]]:
    """A plate 1 cm thick, in front of a wall, and the boxes (lo, hi) of each; with
    ``back_wall``, a wall behind the camera of :func:`test_cone_starts_never_pass_a_surface`
    too, so that the camera is inside the field's bounds."""
    boxes = [(np.array([-0.3, -1.005, -0.2]), np.array([0.3, -0.995, 0.2])),
             (np.array([-2.0, 1.0, -2.0]), np.array([2.0, 1.2, 2.0]))]
    if back_wall:
        boxes.append((np.array([-2.0, -3.6, -2.0]), np.array([2.0, -3.5, 2.0])))
    colours = [(0.9, 0.2, 0.1), (0.2, 0.3, 0.9), (0.5, 0.5, 0.5)]
    fields = [Box(tuple((hi - lo) / 2), tuple((hi + lo) / 2), color=c) for (lo, hi), c in zip(boxes, colours)]
    return Union(*fields), boxes


@pytest.mark.parametrize("tile", [2, 3, 8])
@pytest.mark.parametrize("camera_inside", [False, True])
def test_cone_starts_never_pass_a_surface(tile: int, camera_inside: bool) -> None:
    # Tiles cut by the plate's edges: some of their rays hit the plate, 2 m before the wall
    # that their axis may see. No ray may start past its first surface (closed form), and
    # the cones must still save most of the way (a cone that never moved passes trivially).
    field, boxes = plate_before_wall(camera_inside)
    assert bool((field.bounds[0] < torch.tensor([0.1, -3.0, 0.05])).all()) == camera_inside
    n, f = 96, 70.0
    o, d, _ = pinhole_rays(intrinsics(f, n, n), look_at(np.array([0.1, -3.0, 0.05]), np.array([0.0, 0.0, 0.0])),
                           n, n, device=CPU)
    t_min, evals = cone_starts(field, o, d, pixel_tiles(n, n, tile), SphereTracerConfig())
    on, dn = o.double().numpy(), d.double().numpy()
    first = np.full(len(on), np.inf)
    for lo, hi in boxes:
        hit, t_in, _ = ray_box(on, dn, lo, hi)
        first = np.where(hit, np.minimum(first, t_in), first)
    plate = ray_box(on, dn, *boxes[0])[0]
    wall = np.isfinite(first) & ~plate
    assert 0 < plate.sum() < wall.sum() < len(on)
    start = t_min.double().numpy()
    assert (start[plate | wall] <= first[plate | wall] + 1e-6).all()
    # The plate's rays start in front of it, the wall's most of their way there.
    assert np.median(start[plate] / first[plate]) > 0.5
    assert np.median(start[wall] / first[wall]) > 0.5
    assert evals.shape == (math.ceil(n / tile) ** 2,) and int(evals.min()) >= 1


def test_cone_starts_need_one_apex() -> None:
    # A tile whose rays leave different points is not a cone: its rays start where they would.
    field, _ = plate_before_wall()
    o = torch.tensor([[0.0, -3.0, 0.0], [0.0, -3.0, 0.0], [0.5, -3.0, 0.0], [0.5, -3.0, 0.0]])
    d = torch.tensor([[0.0, 1.0, 0.0]] * 4)
    t_min, evals = cone_starts(field, o, d, torch.tensor([0, 0, 1, 1]))
    assert torch.isfinite(t_min).all() and bool((t_min > 1.0).all())
    t_min, evals = cone_starts(field, o, d, torch.tensor([0, 1, 0, 1]))
    assert bool(torch.isneginf(t_min).all()) and int(evals.sum()) == 0


def test_pixel_tiles() -> None:
    np.testing.assert_array_equal(pixel_tiles(5, 3, 2).numpy(),
                                  [0, 0, 1, 1, 2, 0, 0, 1, 1, 2, 3, 3, 4, 4, 5])
    with pytest.raises(ValueError, match="cone_tile"):
        SphereTracerConfig(cone_tile=-1)


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_render_with_cones_is_render_without(config: SphereTracerConfig) -> None:
    # The cones change where rays start, not what they hit: the same pixels, surfaces and
    # colours, depths within the tolerance, and fewer evaluations, the cones' own included.
    field, _ = plate_before_wall()
    cam = Camera(intrinsics(70.0, 96, 72), 96, 72, look_at(np.array([0.1, -3.0, 0.05]), np.zeros(3)))
    off = render(field, cam, dataclasses.replace(config, cone_tile=0))
    on = render(field, cam, dataclasses.replace(config, cone_tile=3))
    assert torch.equal(off.mask, on.mask) and torch.equal(off.instance_id, on.instance_id)
    torch.testing.assert_close(on.depth, off.depth, atol=1e-4, rtol=0)
    torch.testing.assert_close(on.rgb, off.rgb, atol=1e-6, rtol=0)
    assert int(on.evals_per_pixel.sum()) < 0.95 * int(off.evals_per_pixel.sum())


def test_cone_starts_from_outside_the_bounds() -> None:
    # A camera outside the bounds, aimed at a ball off to the side of the bounds' nearest
    # face: the cone must end in front of the ball, and most of the way to it. Rays of one
    # small tile, first hits in closed form.
    field = Union(Sphere(0.1, (0.6, 0.0, 0.0)), Sphere(0.02, (-0.6, 0.5, 0.0)))
    eye = np.array([0.0, -1.0, 0.0])
    o, d, _ = pinhole_rays(intrinsics(400.0, 4, 4), look_at(eye, np.array([0.6, 0.0, 0.0])), 4, 4, device=CPU)
    assert float(field.bounds[0, 1]) > -0.2 and float(field.bounds[0, 0]) < -0.5
    t_min, evals = cone_starts(field, o, d, torch.zeros(16, dtype=torch.long))
    hit, t_hit, _ = ray_sphere(o.double().numpy(), d.double().numpy(), np.array([0.6, 0.0, 0.0]), 0.1)
    assert hit.all()
    start = t_min.double().numpy()
    assert (start <= t_hit).all() and (start > 0.9 * t_hit).all()
    assert int(evals.sum()) >= 2


def test_render_many_without_normals() -> None:
    # Callers that keep no normals skip their gradients: the same colour, depth and ids.
    field, _ = plate_before_wall()
    cam = Camera(intrinsics(70.0, 48, 36), 48, 36, look_at(np.array([0.1, -3.0, 0.05]), np.zeros(3)))
    (with_n,), (without,) = render_many(field, [cam]), render_many(field, [cam], normals=False)
    assert without.normals is None and with_n.normals is not None
    for name in ("rgb", "depth", "instance_id", "mask", "evals_per_pixel"):
        assert torch.equal(getattr(with_n, name), getattr(without, name))
