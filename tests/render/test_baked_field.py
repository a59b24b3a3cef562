"""Baked fields against the analytic fields they were baked from."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from regnf.fields.analytic import Sphere, Union
from regnf.render.baked_field import BakeConfig, BakedField, bake, bake_cell, grid_nodes
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.render.sphere_tracer import SphereTracerConfig

RED, BLUE = (0.9, 0.1, 0.1), (0.1, 0.2, 0.9)
CELL = 0.02


def two_spheres() -> Union:
    return Union(Sphere(0.4, (-0.3, 0.0, 0.0), color=RED), Sphere(0.3, (0.45, 0.0, 0.1), color=BLUE), name="pair")


def truth(x: np.ndarray) -> np.ndarray:
    return np.minimum(np.linalg.norm(x - [-0.3, 0.0, 0.0], axis=1) - 0.4,
                      np.linalg.norm(x - [0.45, 0.0, 0.1], axis=1) - 0.3)


@pytest.fixture(scope="module")
def baked() -> BakedField:
    return bake(two_spheres(), CELL)


def test_distance_inside_the_bounds_is_the_sources_near_the_surface_and_a_lower_bound_away(baked: BakedField) -> None:
    lo, hi = baked.bounds.numpy()
    x = np.random.default_rng(0).uniform(lo, hi, size=(20000, 3))
    d = baked.sdf(torch.as_tensor(x, dtype=torch.float32)).numpy()
    err = np.abs(d - truth(x))
    near = np.abs(truth(x)) < CELL  # the cells a hit lies in: every corner within the band
    # Trilinear interpolation of a sphere's distance: about h^2 / (8 r) near its surface,
    # more on the crease between the spheres.
    assert np.median(err[near]) < 0.02 * CELL and np.percentile(err[near], 99) < 0.1 * CELL
    # Away from it, the coarse interpolation less its bound (half a 4-cell diagonal).
    slack = 0.5 * np.sqrt(3.0) * 4 * CELL
    far = np.abs(truth(x)) > 3 * CELL + 2 * slack
    assert (np.abs(d[far]) <= np.abs(truth(x)[far]) + 1e-4).all() and (np.sign(d[far]) == np.sign(truth(x)[far])).all()
    assert err[far].max() < 2 * slack
    assert baked.nodes == grid_nodes(baked.bounds, CELL, 4)


def test_the_coarse_pass_changes_nothing_within_the_band(baked: BakedField) -> None:
    full = bake(two_spheres(), CELL, BakeConfig(coarse_stride=1))
    assert full.nodes == grid_nodes(full.bounds, CELL)
    if full.nodes == baked.nodes:  # the same lattice: the nodes within the band agree exactly
        band = full.sdf_grid.abs() <= 2 * CELL
        assert torch.equal(full.sdf_grid[band], baked.sdf_grid[band])
        assert torch.equal(full.rgb_grid[:, :, band[0, 0]], baked.rgb_grid[:, :, band[0, 0]])
    lo, hi = baked.bounds.numpy()
    x = torch.as_tensor(np.random.default_rng(4).uniform(lo, hi, size=(5000, 3)), dtype=torch.float32)
    near = torch.as_tensor(np.abs(truth(x.numpy())) < 1.5 * CELL)
    np.testing.assert_allclose(full.sdf(x)[near].numpy(), baked.sdf(x)[near].numpy(), atol=0.05 * CELL)


def test_outside_the_bounds_it_is_a_lower_bound_of_the_distance(baked: BakedField) -> None:
    lo, hi = baked.bounds.numpy()
    rng = np.random.default_rng(1)
    x = rng.uniform(lo - 1.0, hi + 1.0, size=(5000, 3))
    x = x[(x < lo).any(axis=1) | (x > hi).any(axis=1)]
    d = baked.sdf(torch.as_tensor(x, dtype=torch.float32)).numpy()
    outside = np.linalg.norm(x - np.clip(x, lo, hi), axis=1)
    assert (d >= outside - 1e-5).all()  # at least the way back into the bounds
    assert (d <= truth(x) + 1e-4).all()  # never past a surface


def test_colour_at_the_surface_is_the_sources(baked: BakedField) -> None:
    rng = np.random.default_rng(2)
    u = rng.normal(size=(500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    red = np.array([-0.3, 0.0, 0.0]) + 0.4 * u
    red = red[red[:, 0] < -0.05]  # away from the other sphere
    c = baked.color(torch.as_tensor(red, dtype=torch.float32)).numpy()
    # Kept to half precision: at most 2.4e-4 off in [0, 1] (RGB_STORAGE).
    np.testing.assert_allclose(c, np.broadcast_to(RED, c.shape), atol=2.5e-4)


def test_bake_cell_follows_the_pixel_footprint_and_the_node_cap() -> None:
    field = two_spheres()
    K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]])
    pose = np.eye(4)
    pose[:3, 3] = field.bounds.numpy().mean(axis=0) + [0.0, 0.0, -2.0]  # 2 units from the centre
    cam = Camera(K, 64, 48, pose)
    assert bake_cell(field, [cam], BakeConfig(cell_pixels=1.0)) == pytest.approx(2.0 / 100.0)
    assert bake_cell(field, [cam]) == pytest.approx(1.0 / 100.0)  # half a footprint by default
    capped = bake_cell(field, [cam], BakeConfig(max_nodes=1000))
    assert math.prod(grid_nodes(field.bounds, capped, 4)) <= 1000 < math.prod(grid_nodes(field.bounds, capped / 1.02, 4))
    with pytest.raises(ValueError, match="max_nodes"):
        bake(field, capped / 2, BakeConfig(max_nodes=1000))
    with pytest.raises(ValueError, match="band_cells"):
        BakeConfig(band_cells=1.0)
    with pytest.raises(ValueError, match="coarse_stride"):
        BakeConfig(coarse_stride=0)


def _camera() -> Camera:
    K = np.array([[60.0, 0.0, 24.0], [0.0, 60.0, 18.0], [0.0, 0.0, 1.0]])
    pose = np.eye(4)  # OpenCV axes looking along +y
    pose[:3, :3] = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    pose[:3, 3] = [0.05, -2.0, 0.05]
    return Camera(K, 48, 36, pose)


def test_sphere_traced_baked_field_renders_the_source_and_a_shifted_grid_does_not(baked: BakedField) -> None:
    cfg = SphereTracerConfig.plain()
    exact = render(two_spheres(), _camera(), cfg)
    shifted = BakedField(baked.sdf_grid[0, 0], baked.rgb_grid[0], baked.bounds + 3 * CELL, baked.to_world, baked.info)
    depth_err = []
    for f in (baked, shifted):
        out = render(f, _camera(), cfg)
        both = exact.mask & out.mask
        depth_err.append(np.percentile((out.depth - exact.depth)[both].abs().numpy(), 95))
        if f is baked:
            assert float((out.mask != exact.mask).float().mean()) < 0.01
            assert float((out.rgb - exact.rgb)[both].abs().max()) < 1e-3
    # Measured: 0.04 cells (0.33 at most, on grazing rays at the silhouette).
    assert depth_err[0] < 0.1 * CELL
    assert depth_err[1] > 2 * CELL  # the check sees a grid read a few cells off


@pytest.mark.cuda
def test_a_bake_on_the_device_is_the_cpu_bake(baked: BakedField, device: str) -> None:
    """Baking and tracing on ``--device`` give the CPU's grid and image (to float rounding)."""
    on = bake(two_spheres().to(device), CELL)
    assert on.sdf_grid.device.type == torch.device(device).type
    torch.testing.assert_close(on.sdf_grid.cpu(), baked.sdf_grid, atol=1e-5, rtol=0)
    torch.testing.assert_close(on.rgb_grid.cpu(), baked.rgb_grid, atol=1e-5, rtol=0)
    cfg = SphereTracerConfig.plain()
    a, b = render(baked, _camera(), cfg), render(on, _camera(), cfg)
    assert float((a.mask != b.mask.cpu()).float().mean()) < 0.002
    both = a.mask & b.mask.cpu()
    assert float((a.depth - b.depth.cpu())[both].abs().max()) < 1e-3 * CELL
