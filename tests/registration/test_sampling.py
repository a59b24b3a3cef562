"""Multi-view surface sampling on analytic scenes with known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from regnf.fields.analytic import Transformed
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.fields.similarity import similarity_matrix
from regnf.registration.sampling import (
    SamplingConfig,
    SurfaceSamples,
    camera_rig,
    sample_surface,
    view_directions,
)

from .fixtures import OBJECT_HI, OBJECT_LO, make_object, make_scene, object_box, placement, rot

M_PLACE = placement([0, 0, 1], 0.7, [0.5, -0.3, 0.0], 1.3)  # yaw, on the floor, scaled


def fd_normals(field: Field, p: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Unit normals by float64 central differences (independent of autograd)."""
    x = torch.as_tensor(p, dtype=torch.float64)
    g = np.stack(
        [
            (field.sdf(x + h * e) - field.sdf(x - h * e)).numpy() / (2 * h)
            for e in torch.eye(3, dtype=torch.float64)
        ],
        axis=1,
    )
    return g / np.linalg.norm(g, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def scene_samples() -> tuple[Field, OrientedBox, SurfaceSamples]:
    scene = make_scene(M_PLACE)
    box = object_box().transformed(M_PLACE)
    return scene, box, sample_surface(scene, box, SamplingConfig(), side="scene")


def test_scene_points_are_on_the_object_inside_the_box(scene_samples) -> None:
    scene, box, s = scene_samples
    assert s.points.dtype == np.float64 and s.points.shape == s.normals.shape
    assert 1000 < len(s.points) <= 5000
    sdf = scene.sdf(torch.as_tensor(s.points)).numpy()
    assert np.abs(sdf).max() < 1e-4
    assert box.contains(s.points, pad_rel=0.1).all()
    # No floor left: every point lies on the placed object itself, none on the slab only.
    obj = Transformed(make_object(), M_PLACE)
    on_object = np.abs(obj.sdf(torch.as_tensor(s.points)).numpy()) < 1e-4
    assert on_object.all()
    assert np.isin(np.arange(5), s.view_ids).all()


def test_scene_normals_match_analytic(scene_samples) -> None:
    _, _, s = scene_samples
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-6)
    obj = Transformed(make_object(), M_PLACE)
    ref = fd_normals(obj, s.points)
    angle = np.degrees(np.arccos(np.clip((ref * s.normals).sum(axis=1), -1, 1)))
    # Edges and the union's creases have no unique normal: allow a sliver of outliers.
    assert np.quantile(angle, 0.99) < 1.0


def test_floor_without_removal_is_kept() -> None:
    scene = make_scene(M_PLACE)
    box = object_box().transformed(M_PLACE)
    s = sample_surface(scene, box, SamplingConfig(remove_floor=False, rays_per_side=32), "scene")
    floor = (np.abs(s.points[:, 2]) < 1e-4) & (s.normals[:, 2] > 0.999)
    assert floor.sum() > 20


def test_floor_removal_follows_the_up_parameter() -> None:
    # The whole room turned so that its floor normal is +Y.
    R = rot([1, 0, 0], -math.pi / 2)  # z -> y
    turn = similarity_matrix(R, np.zeros(3), 1.0)
    scene = Transformed(make_scene(M_PLACE), turn)
    box = object_box().transformed(turn @ M_PLACE)
    cfg = SamplingConfig(up=(0.0, 1.0, 0.0), rays_per_side=32)
    s = sample_surface(scene, box, cfg, "scene")
    obj = Transformed(make_object(), turn @ M_PLACE)
    assert (np.abs(obj.sdf(torch.as_tensor(s.points)).numpy()) < 1e-4).all()


def test_undersides_are_dropped_on_the_scene_side_only() -> None:
    """The lower half of the test object's ball faces down: the side cameras see it, and the
    scene side drops the hits whose normal lies within ``underside_deg`` of down (``up``
    turned with the room), the library side keeps them."""
    down_cos = math.cos(math.radians(60.0))
    R = rot([1, 0, 0], -math.pi / 2)  # z -> y
    turn = similarity_matrix(R, np.zeros(3), 1.0)
    for M, up in ((M_PLACE, (0.0, 0.0, 1.0)), (turn @ M_PLACE, (0.0, 1.0, 0.0))):
        scene = Transformed(make_scene(M_PLACE), M @ np.linalg.inv(M_PLACE))
        box = object_box().transformed(M)
        cfg = SamplingConfig(up=up, rays_per_side=32)
        kept = sample_surface(scene, box, cfg, "scene")
        every = sample_surface(scene, box, SamplingConfig(up=up, rays_per_side=32, underside_deg=0.0), "scene")
        assert (every.normals @ np.asarray(up) < -down_cos).sum() > 10
        assert (kept.normals @ np.asarray(up) >= -down_cos).all()
        # What is left of the object: the rest of it, the ball's upper half included.
        assert (kept.normals @ np.asarray(up) > down_cos).sum() > 10
    lib = sample_surface(make_object(), None, SamplingConfig(rays_per_side=32), "library")
    assert (lib.normals[:, 2] < -down_cos).sum() > 5
    with pytest.raises(ValueError, match="underside_deg"):
        SamplingConfig(underside_deg=90.0)


def test_library_covers_the_whole_object() -> None:
    lib = make_object()
    s = sample_surface(lib, None, SamplingConfig(), side="library")
    assert np.abs(lib.sdf(torch.as_tensor(s.points)).numpy()).max() < 1e-4
    assert np.isin(np.arange(5), s.view_ids).all()
    # The cloud spans the object's box (the bottom face is seen by no camera: z from 0+).
    np.testing.assert_allclose(s.points.min(axis=0), OBJECT_LO, atol=0.02)
    np.testing.assert_allclose(s.points.max(axis=0), OBJECT_HI, atol=0.02)
    # Every part of the union is sampled.
    for part in lib.fields:
        assert (np.abs(part.sdf(torch.as_tensor(s.points)).numpy()) < 1e-4).sum() > 50


def test_camera_distance_and_fov_scale_with_the_box() -> None:
    cfg = SamplingConfig()
    box = OrientedBox(np.array([1.0, 2.0, 0.5]), np.array([0.3, 0.2, 0.5]), rot([0, 0, 1], 0.3))
    big = OrientedBox(box.center, 3.0 * box.half_extents, box.rotation)
    for b in (box, big):
        rig = camera_rig(b, cfg)
        eyes = rig.camtoworld[:, :3, 3]
        np.testing.assert_allclose(
            np.linalg.norm(eyes - b.center, axis=1), cfg.distance_factor * b.radius
        )
        # Every camera looks at the centre (OpenCV: +z forward).
        fwd = rig.camtoworld[:, :3, 2]
        np.testing.assert_allclose(
            fwd,
            (b.center - eyes) / np.linalg.norm(b.center - eyes, axis=1, keepdims=True),
            atol=1e-12,
        )
        # A proper rotation per camera (no mirrored images).
        np.testing.assert_allclose(np.linalg.det(rig.camtoworld[:, :3, :3]), 1.0, atol=1e-12)
    np.testing.assert_allclose(camera_rig(box, cfg).K, camera_rig(big, cfg).K)
    # The field of view just contains the box's bounding sphere.
    rig = camera_rig(box, cfg)
    half = math.atan(0.5 * rig.size / rig.K[0, 0])
    assert math.sin(half) == pytest.approx(cfg.fov_margin / cfg.distance_factor)


def test_view_directions() -> None:
    five = view_directions(SamplingConfig())
    np.testing.assert_allclose(
        five, [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], atol=0
    )
    fib = view_directions(SamplingConfig(n_views=12))
    assert fib.shape == (12, 3)
    np.testing.assert_allclose(np.linalg.norm(fib, axis=1), 1.0)
    assert (fib[:, 2] >= 0).all()  # the upper hemisphere (and the equator)
    assert view_directions(SamplingConfig(views="single")).shape == (1, 3)


def test_empty_box_raises() -> None:
    scene = make_scene(M_PLACE)
    empty = OrientedBox(np.array([2.0, 2.0, 1.5]), np.array([0.2, 0.2, 0.2]))
    with pytest.raises(ValueError, match="contains no surface"):
        sample_surface(scene, empty, SamplingConfig(rays_per_side=16), "scene")
    with pytest.raises(ValueError, match="proposal box"):
        sample_surface(scene, None, SamplingConfig(), "scene")
    with pytest.raises(ValueError, match="side"):
        sample_surface(scene, empty, SamplingConfig(), "world")  # type: ignore[arg-type]


def test_single_view_sees_one_side_only() -> None:
    scene = make_scene(M_PLACE)
    box = object_box().transformed(M_PLACE)
    cfg = SamplingConfig(views="single")
    s = sample_surface(scene, box, cfg, "scene")
    assert len(s.points) > 100 and (s.view_ids == 0).all()
    eye = camera_rig(box.inflated(cfg.box_inflate), cfg).camtoworld[0, :3, 3]
    # Every point faces the single camera, and the far (+y) faces are not in the cloud.
    assert ((s.normals * (eye - s.points)).sum(axis=1) > 0).all()
    multi = sample_surface(scene, box, SamplingConfig(), "scene")
    assert len(s.points) < 0.6 * len(multi.points)


def test_deterministic_and_capped() -> None:
    lib = make_object()
    cfg = SamplingConfig(max_points=700, rays_per_side=48)
    a = sample_surface(lib, None, cfg, "library")
    b = sample_surface(lib, None, cfg, "library")
    assert len(a.points) == 700
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


class NaNField(Field):
    """A broken field: NaN everywhere."""

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return torch.full((x.shape[0],), float("nan"), dtype=x.dtype)

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        return torch.full((x.shape[0], 3), 0.5, dtype=x.dtype)


def test_non_finite_field_raises() -> None:
    box = OrientedBox.from_aabb(-0.5 * np.ones(3), 0.5 * np.ones(3))
    with pytest.raises(ValueError, match="non-finite"):
        sample_surface(NaNField(), box, SamplingConfig(rays_per_side=8), "scene")


def test_bad_config_raises() -> None:
    with pytest.raises(ValueError, match="distance_factor"):
        SamplingConfig(distance_factor=0.9)
    with pytest.raises(ValueError, match="views"):
        SamplingConfig(views="few")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="up"):
        SamplingConfig(up=(0.0, 0.0, 0.0))
