"""The composite field against closed-form SDFs of the expected geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from regnf.compositor import CompositeConfig, CompositeField
from regnf.compositor.placement import PlacedObject
from regnf.compositor.regions import BoxRegionUnion, OrientedBoxRegion, ShellRegion
from regnf.fields.analytic import Box, Sphere, Union
from regnf.fields.field import Field
from regnf.fields.similarity import similarity_matrix

from . import helpers as H


def make_composite(cull: bool = True, tint=None) -> CompositeField:
    region = OrientedBoxRegion(
        H.REGION_CENTER,
        H.REGION_HALF,
        H.REGION_ROT,
        keep_floor=H.FLOOR_Z,
        floor_margin=H.FLOOR_MARGIN,
    )
    placed = PlacedObject(H.library_sphere(), H.LIB_TO_SCENE, H.INSTANCE, tint)
    return CompositeField(H.scene_field(), [placed], [region], CompositeConfig(cull=cull))


def test_composite_is_a_field_in_the_scene_frame() -> None:
    comp = make_composite()
    scene = H.scene_field()
    assert isinstance(comp, Field)
    assert torch.equal(comp.to_world, scene.to_world)
    assert bool(
        (comp.bounds[0] <= scene.bounds[0]).all() and (comp.bounds[1] >= scene.bounds[1]).all()
    )
    assert comp.instance_ids == (H.INSTANCE,)


def test_exact_composite_matches_closed_form() -> None:
    x = H.random_points(4000, seed=1)
    got = make_composite(cull=False).sdf(H.tensor(x)).numpy()
    np.testing.assert_allclose(got, H.composite_truth(x), atol=1e-5, rtol=0)


def test_scale_direction_library_distances_grow_with_the_object() -> None:
    comp = make_composite(cull=False)
    u = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    pts = np.stack([H.PLACED_CENTER, H.PLACED_CENTER + 0.5 * u, H.PLACED_CENTER + 0.2 * u])
    got = comp.sdf(H.tensor(pts)).numpy()
    # Radius 0.1 in the library frame, scale 2: radius 0.2 and distances in scene units.
    np.testing.assert_allclose(got, [-0.2, 0.3, 0.0], atol=1e-9)
    assert comp.scale_of(H.INSTANCE) == pytest.approx(2.0)


@pytest.mark.parametrize("cull", [False, True])
def test_sign_matches_the_expected_geometry(cull: bool) -> None:
    x = H.random_points(6000, seed=2)
    want = H.expected_geometry_sdf(x)
    keep = np.abs(want) > 1e-3
    got = make_composite(cull=cull).sdf(H.tensor(x)).numpy()
    assert np.array_equal(np.sign(got[keep]), np.sign(want[keep]))


def test_floor_survives_inside_the_removal_box() -> None:
    comp = make_composite()
    rng = np.random.default_rng(3)
    local = rng.uniform(-0.35, 0.35, size=(500, 2))  # inside the rotated box footprint
    xy = local @ H.REGION_ROT[:2, :2].T + H.REGION_CENTER[:2]
    top = np.column_stack([xy, np.zeros(len(xy))])
    sample = comp.evaluate(H.tensor(top))
    np.testing.assert_allclose(sample.sdf.numpy(), 0.0, atol=1e-9)
    assert bool((sample.winner == 0).all())
    below = top - np.array([0.0, 0.0, 0.05])
    assert bool((comp.sdf(H.tensor(below)) < 0).all())
    # The removed object: its centre and its surface are now empty space.
    old = np.array([H.OBJ_CENTER, H.OBJ_CENTER + [0.0, 0.0, H.OBJ_RADIUS]])
    assert bool((comp.sdf(H.tensor(old)) > 0.05).all())


def test_winner_ids() -> None:
    comp = make_composite()
    rng = np.random.default_rng(4)
    u = rng.normal(size=(200, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    on_ball = H.PLACED_CENTER + (H.PLACED_RADIUS + 1e-4) * u
    on_floor = np.column_stack([rng.uniform(-1.8, -1.0, size=(200, 2)), np.full(200, 1e-4)])
    assert bool((comp.evaluate(H.tensor(on_ball)).winner == H.INSTANCE).all())
    assert bool((comp.evaluate(H.tensor(on_floor)).winner == 0).all())
    plain = H.scene_field().evaluate(H.tensor(on_floor))
    assert bool((plain.winner == 0).all() and (plain.evals == 1).all())


def test_culling_is_conservative_exact_near_surfaces_and_cheaper() -> None:
    x = H.tensor(H.random_points(6000, seed=5))
    exact = make_composite(cull=False).evaluate(x)
    culled = make_composite(cull=True).evaluate(x)
    e, c = exact.sdf.numpy(), culled.sdf.numpy()
    assert np.array_equal(np.sign(c), np.sign(e))
    assert bool((np.abs(c) <= np.abs(e) + 1e-12).all())  # a lower bound: safe steps
    near = np.abs(e) < CompositeConfig().cull_pad
    assert near.sum() > 50
    np.testing.assert_allclose(c[near], e[near], atol=1e-12)
    # Exact: scene + object everywhere; culled: the object only inside its padded box, the
    # scene only where it is not deeper than cull_pad inside the removal region.
    assert bool((exact.evals == 2).all())
    assert int(culled.evals.sum()) < 0.7 * int(exact.evals.sum())
    comp = make_composite(cull=True)
    deep = (-comp.removals[0].evaluate(x).sdf > CompositeConfig().cull_pad).numpy()
    assert deep.sum() > 50 and (~deep).sum() > 50
    in_box = (comp.placements[0].box.sdf(x) <= CompositeConfig().cull_pad).numpy()
    np.testing.assert_array_equal(culled.evals.numpy(), (~deep).astype(int) + in_box.astype(int))


def _shell_scene() -> tuple[Field, ShellRegion, ShellRegion]:
    floor = Box(H.FLOOR_HALF, H.FLOOR_CENTER, name="floor")
    wall = Box((0.05, 2.0, 1.0), (1.0, 0.0, 1.0), name="wall")  # face at x = 0.95
    obj = Sphere(0.3, (0.6, 0.0, 0.4), name="obj")  # 5 cm from the wall, 10 cm above the floor
    R = Rotation.from_euler("zyx", [40, 10, -25], degrees=True).as_matrix()
    M = similarity_matrix(R, np.array([0.6, 0.0, 0.4]), 2.0)
    lib = Sphere(0.15, name="lib")  # the registered library twin, half size in its frame
    shells = [ShellRegion(lib, M, dilation=0.02, keep_floor=0.0, cull=c) for c in (True, False)]
    return Union(floor, wall, obj), shells[0], shells[1]


def test_shell_region_removes_the_object_and_keeps_its_neighbours() -> None:
    scene, shell, shell_exact = _shell_scene()
    comp = CompositeField(scene, removals=[shell])
    exact = CompositeField(scene, removals=[shell_exact], config=CompositeConfig(cull=False))
    rng = np.random.default_rng(6)
    u = rng.normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    old_surface = np.array([0.6, 0.0, 0.4]) + 0.3 * u
    assert bool((comp.sdf(H.tensor(old_surface)) > 0.0).all())
    wall_face = np.column_stack(
        [np.full(300, 0.95), rng.uniform(-0.5, 0.5, 300), rng.uniform(0.05, 0.9, 300)]
    )
    floor_top = np.column_stack([rng.uniform(-1.5, 1.5, (300, 2)), np.zeros(300)])
    for surface in (wall_face, floor_top):
        np.testing.assert_allclose(comp.sdf(H.tensor(surface)).numpy(), 0.0, atol=1e-9)
    # Sign of the composite = sign of floor U wall; culled and exact agree near surfaces.
    x = H.random_points(5000, seed=7, lo=(-0.5, -1.0, -0.3), hi=(1.2, 1.0, 1.2))
    want = np.minimum(
        H.box_sdf(x, H.FLOOR_CENTER, H.FLOOR_HALF),
        H.box_sdf(x, np.array([1.0, 0.0, 1.0]), np.array([0.05, 2.0, 1.0])),
    )
    got, ref = comp.sdf(H.tensor(x)).numpy(), exact.sdf(H.tensor(x)).numpy()
    keep = np.abs(want) > 1e-3
    assert np.array_equal(np.sign(got[keep]), np.sign(want[keep]))
    assert bool((np.abs(got) <= np.abs(ref) + 1e-12).all())
    near = np.abs(ref) < 0.02
    np.testing.assert_allclose(got[near], ref[near], atol=1e-12)


def test_colour_comes_from_the_winner_with_multiplicative_tint() -> None:
    tint = (0.5, 1.0, 0.25)
    comp = make_composite(tint=tint)
    rng = np.random.default_rng(8)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    ball = H.tensor(H.PLACED_CENTER + H.PLACED_RADIUS * u)
    floor = H.tensor(np.column_stack([rng.uniform(-1.8, 1.8, (50, 2)), np.zeros(50)]))
    np.testing.assert_allclose(
        comp.color(ball).numpy(), np.tile(np.multiply(H.LIB_COLOR, tint), (50, 1)), atol=1e-6
    )
    np.testing.assert_allclose(
        comp.color(floor).numpy(), np.tile(H.FLOOR_COLOR, (50, 1)), atol=1e-6
    )


class DirectionColour(Sphere):
    """Colour = 0.5 + 0.5 d: shows the view direction the field was queried with."""

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        assert d is not None
        return 0.5 + 0.5 * d


def test_view_directions_are_rotated_into_the_library_frame() -> None:
    lib = DirectionColour(H.LIB_RADIUS, H.LIB_CENTER)
    comp = CompositeField(H.scene_field(), [PlacedObject(lib, H.LIB_TO_SCENE, 3)])
    rng = np.random.default_rng(9)
    u = rng.normal(size=(20, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = rng.normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = comp.color(H.tensor(H.PLACED_CENTER + H.PLACED_RADIUS * u), H.tensor(d)).numpy()
    np.testing.assert_allclose(got, 0.5 + 0.5 * d @ H.LIB_ROT, atol=1e-9)  # R^T d, row-wise


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_through_autograd(dtype: torch.dtype) -> None:
    comp = make_composite()
    rng = np.random.default_rng(10)
    u = rng.normal(size=(100, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    ball = H.PLACED_CENTER + H.PLACED_RADIUS * u
    floor = np.column_stack([rng.uniform(-1.8, -1.0, (100, 2)), np.zeros(100)])
    _, g = comp.sdf_and_gradient(H.tensor(np.vstack([ball, floor]), dtype))
    want = np.vstack([u, np.tile([0.0, 0.0, 1.0], (100, 1))])
    np.testing.assert_allclose(g.double().numpy(), want, atol=1e-5)


def test_bounds_grow_to_hold_objects_outside_the_scene() -> None:
    scene = Sphere(0.5)
    far = similarity_matrix(np.eye(3), np.array([3.0, 0.0, 0.0]), 1.5)
    comp = CompositeField(scene, [PlacedObject(Sphere(0.5), far, 1)])
    assert float(comp.bounds[1, 0]) >= 3.0 + 1.5 * 0.5
    assert float(comp.bounds[0, 0]) <= -0.5


def test_invalid_inputs_are_refused() -> None:
    scene, lib = H.scene_field(), H.library_sphere()
    with pytest.raises(ValueError, match="instance_id"):
        CompositeField(scene, [PlacedObject(lib, H.LIB_TO_SCENE, 0)])
    with pytest.raises(ValueError, match="used twice"):
        CompositeField(
            scene, [PlacedObject(lib, H.LIB_TO_SCENE, 2), PlacedObject(lib, H.LIB_TO_SCENE, 2)]
        )
    with pytest.raises(ValueError, match="tint"):
        CompositeField(scene, [PlacedObject(lib, H.LIB_TO_SCENE, 2, (1.5, 0.0, 0.0))])
    shear = np.eye(4)
    shear[0, 1] = 0.3
    with pytest.raises(ValueError, match="shear"):
        CompositeField(scene, [PlacedObject(lib, shear, 2)])
    with pytest.raises(ValueError, match="half_extents"):
        OrientedBoxRegion((0, 0, 0), (0.1, -0.1, 0.1))
    with pytest.raises(ValueError, match="rotation"):
        OrientedBoxRegion((0, 0, 0), (0.1, 0.1, 0.1), np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="dilation"):
        ShellRegion(lib, H.LIB_TO_SCENE, dilation=-0.1)
    with pytest.raises(ValueError, match="cull_pad"):
        CompositeConfig(cull_pad=0.0)
    with pytest.raises(TypeError):
        CompositeField(scene, removals=[object()])  # type: ignore[list-item]


def test_meshing_and_plain_sphere_tracing_accept_a_composite() -> None:
    from regnf.meshes.meshing import extract_mesh
    from regnf.render.camera import Camera
    from regnf.render.sphere_render import render
    from regnf.render.sphere_tracer import SphereTracerConfig

    comp = make_composite()
    box = np.stack([H.PLACED_CENTER - 0.3, H.PLACED_CENTER + 0.3])
    mesh = extract_mesh(comp, resolution=24, bounds=box, with_color=True)
    radii = np.linalg.norm(mesh.vertices - H.PLACED_CENTER, axis=1)
    np.testing.assert_allclose(radii, H.PLACED_RADIUS, atol=5e-3)
    assert np.allclose(mesh.visual.vertex_colors[:, :3] / 255.0, H.LIB_COLOR, atol=0.01)
    K = np.array([[20.0, 0.0, 8.5], [0.0, 20.0, 8.5], [0.0, 0.0, 1.0]])  # pixel 8 on axis
    pose = np.eye(4)  # OpenCV axes looking along +y: x right = +x, y down = -z, z = +y
    pose[:3, :3] = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    pose[:3, 3] = H.PLACED_CENTER + np.array([0.0, -1.5, 0.0])
    out = render(comp, Camera(K, 16, 16, pose), SphereTracerConfig.plain())  # to_world = I
    assert bool(out.mask[8, 8]) and float(out.depth[8, 8]) == pytest.approx(1.3, abs=1e-3)


def test_removal_boxes_at_once_are_the_regions_one_by_one() -> None:
    rot = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    regions = [OrientedBoxRegion(H.REGION_CENTER, H.REGION_HALF, H.REGION_ROT, keep_floor=H.FLOOR_Z,
                                 floor_margin=H.FLOOR_MARGIN),
               OrientedBoxRegion((0.4, -0.3, 0.2), (0.1, 0.2, 0.3), rot)]  # this one cuts the floor too
    x = H.tensor(H.random_points(5000, seed=7))
    union = BoxRegionUnion(regions).evaluate(x)
    one_by_one = torch.minimum(regions[0].evaluate(x).sdf, regions[1].evaluate(x).sdf)
    np.testing.assert_allclose(union.sdf.numpy(), one_by_one.numpy(), atol=1e-12)
    assert bool((union.evals == 0).all())
    # Both regions matter somewhere, and the floor is spared by the first only.
    inside = [(r.evaluate(x).sdf < 0).numpy() for r in regions]
    assert inside[0].sum() > 20 and inside[1].sum() > 20
    # A composite with box removals uses the union; with another kind of region, the loop.
    assert make_composite().removal_union is not None
    scene, shell, _ = _shell_scene()
    assert CompositeField(scene, removals=[shell]).removal_union is None
