"""The baked composite against the composite it was baked from (analytic fields)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from regnf.compositor import CompositeConfig, CompositeField
from regnf.compositor.baked_composite import bake_for_views
from regnf.compositor.placement import PlacedObject
from regnf.compositor.regions import OrientedBoxRegion
from regnf.fields.similarity import similarity_matrix
from regnf.render.baked_field import BakeConfig, BakedField
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.render.sphere_tracer import SphereTracerConfig

from . import helpers as H


def two_instances() -> CompositeField:
    """The helpers' scene less its removal box, with the library sphere placed twice (one field)."""
    region = OrientedBoxRegion(H.REGION_CENTER, H.REGION_HALF, H.REGION_ROT, keep_floor=H.FLOOR_Z,
                               floor_margin=H.FLOOR_MARGIN)
    ball = H.library_sphere()
    second = similarity_matrix(np.eye(3), [0.9, -0.5, 0.0]) @ H.LIB_TO_SCENE
    placed = [PlacedObject(ball, H.LIB_TO_SCENE, H.INSTANCE), PlacedObject(ball, second, 9, (0.5, 1.0, 1.0))]
    return CompositeField(H.scene_field(), placed, [region], CompositeConfig())


def camera() -> Camera:
    K = np.array([[40.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
    pose = np.eye(4)  # OpenCV axes looking along +y, from above the floor
    pose[:3, :3] = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    pose[:3, 3] = [0.0, -2.5, 0.5]
    return Camera(K, 64, 48, pose)


def test_removals_go_into_the_scene_grid_and_each_library_field_is_baked_once() -> None:
    comp = two_instances()
    out = bake_for_views(comp, [camera()], BakeConfig())
    baked = out.field
    assert len(baked.removals) == 0 and isinstance(baked.scene, BakedField)
    fields = [p.field for p in baked.placements]
    assert all(isinstance(f, BakedField) for f in fields) and fields[0] is fields[1]
    assert baked.instance_ids == comp.instance_ids and baked.tints == comp.tints
    assert out.nodes == baked.scene.sdf_grid.numel() + fields[0].sdf_grid.numel()
    # The distances agree near the surfaces, the removal box's cut included. The reference is
    # the composite evaluated everywhere: culled, it is exact only within cull_pad (0.02) of a
    # surface, and this band is wider.
    x = torch.as_tensor(H.random_points(20000, seed=3), dtype=torch.float32)
    unculled = CompositeField(comp.scene, comp.placed(), list(comp.removals), CompositeConfig(cull=False))
    exact, approx = unculled.evaluate(x), baked.evaluate(x)
    near = exact.sdf.abs() < 0.05
    cell = float(baked.scene.info.provenance["baked"]["cell"])
    err = (approx.sdf - exact.sdf)[near].abs()
    assert float(err.median()) < 0.05 * cell and float(err.max()) < 1.5 * cell
    assert float((approx.winner[near] == exact.winner[near]).float().mean()) > 0.98


def test_the_baked_composite_renders_the_composite() -> None:
    comp = two_instances()
    baked = bake_for_views(comp, [camera()], BakeConfig()).field
    cfg = SphereTracerConfig.plain()
    exact, approx = render(comp, camera(), cfg), render(baked, camera(), cfg)
    assert float((exact.instance_id != approx.instance_id).float().mean()) < 0.01
    both = exact.mask & approx.mask
    assert float((exact.rgb - approx.rgb)[both].abs().amax(dim=-1).median()) < 1e-3
    assert float((exact.depth - approx.depth)[both].abs().median()) < 1e-3


def test_a_bake_larger_than_the_total_cap_is_refused_before_any_baking(monkeypatch) -> None:
    import regnf.compositor.baked_composite as B

    baked: list[str] = []
    monkeypatch.setattr(B, "bake", lambda f, *a, **k: baked.append(f.name))

    # The scene takes about 620 000 nodes and the ball 729 at the default cell.
    with pytest.raises(ValueError, match="grid nodes.*max_total_nodes"):
        bake_for_views(two_instances(), [camera()], BakeConfig(max_total_nodes=600_000))
    assert baked == []


def test_a_baked_composite_is_not_baked_again() -> None:
    once = bake_for_views(two_instances(), [camera()], BakeConfig())
    again = bake_for_views(once.field, [camera()], BakeConfig())
    assert again.field is once.field and again.seconds == 0.0 and again.nodes == once.nodes


def test_a_library_field_is_baked_for_where_it_stands_in_the_scene() -> None:
    """Its cell is the pixel footprint at its place, in its own units: twice as far, twice the
    cell; placed twice as large, half the cell (in library units)."""
    from regnf.render.baked_field import bake_cell

    ball = H.library_sphere()
    cam = camera()
    eye = np.asarray(cam.camera_to_world)[:3, 3]
    centre = ball.bounds.mean(dim=0).double().numpy()

    def at(distance: float, scale: float) -> np.ndarray:
        W = similarity_matrix(np.eye(3), [0.0, 0.0, 0.0], scale)
        W[:3, 3] = eye + [0.0, distance, 0.0] - scale * centre
        return W

    cfg = BakeConfig(max_nodes=2**30)
    near, far, large = (bake_cell(ball, [cam], cfg, to_world=at(d, s)) for d, s in ((2.0, 1.0), (4.0, 1.0), (2.0, 2.0)))
    assert near == pytest.approx(cfg.cell_pixels * 2.0 / 40.0, rel=1e-6)
    assert far == pytest.approx(2 * near, rel=1e-6) and large == pytest.approx(near / 2, rel=1e-6)
