"""NeuralSDF: geometric initialisation, gradients, heads, encodings and the config."""

from __future__ import annotations

import math

import pytest
import torch

from regnf.core.box_grid import grid_shape
from regnf.fields.analytic import Box, Sphere
from regnf.fields.dense_grid import DenseGridEncoding, level_resolutions
from regnf.fields.hash_grid import HashGridEncoding
from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig, tetrahedral_gradient

SMALL = NeuralSDFConfig(
    levels=3,
    features_per_level=2,
    base_resolution=8,
    finest_resolution=24,
    hidden_dim=32,
    geo_feature_dim=7,
    color_hidden_dim=16,
)


def unit_dirs(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1)


def randomised(field: NeuralSDF, seed: int = 0, std: float = 0.3) -> NeuralSDF:
    """Every parameter random, so the grid features matter (at init they are ~1e-4 and the
    first layer ignores them)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in field.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * std)
    return field


# -- geometric initialisation -------------------------------------------------------------------
@pytest.mark.parametrize("radius", [0.5, 0.3])
def test_geometric_init_is_roughly_a_sphere(radius: float) -> None:
    """The SAL initialisation makes the SDF ~ |x| - radius.

    A 2 x 64 MLP approximates the norm only statistically (the width averages random
    features), so the bounds are loose but seed-robust: over seeds 0-9 the median zero
    crossing along rays is within 0.1 of the radius, the value at the centre within
    [-r - 0.05, -r + 0.2] (softplus(0) > 0 lifts it) and the radial slope within 0.8-1.25.
    """
    torch.manual_seed(0)
    field = NeuralSDF(NeuralSDFConfig(init_radius=radius))
    dirs = unit_dirs(200)
    t = torch.linspace(0.0, 0.99, 500)
    with torch.no_grad():
        s = field.sdf((dirs[:, None, :] * t[None, :, None]).reshape(-1, 3)).view(200, -1)
    centre = float(s[:, 0].mean())
    assert -radius - 0.05 < centre < -radius + 0.2
    assert (s[:, 0] < 0).all()  # inside at the centre
    assert (s[:, -1] > 0).float().mean() > 0.95  # outside near the bounds' faces
    crossing = t[(s > 0).float().argmax(dim=1)]
    assert abs(float(crossing.median()) - radius) < 0.1
    # The direction-averaged profile is a distance: slope ~1 well outside the sphere.
    profile = s.mean(0)
    slope = float((profile[-1] - profile[300]) / (t[-1] - t[300]))
    assert 0.8 < slope < 1.25
    # A larger init radius gives a smaller value everywhere (the bias is -radius).
    torch.manual_seed(0)
    other = NeuralSDF(NeuralSDFConfig(init_radius=radius + 0.2))
    x = dirs * 0.6
    with torch.no_grad():
        torch.testing.assert_close(other.sdf(x), field.sdf(x) - 0.2, atol=1e-6, rtol=0)


def test_inside_out_flips_the_sign() -> None:
    torch.manual_seed(3)
    normal = NeuralSDF(NeuralSDFConfig(init_radius=0.7))
    torch.manual_seed(3)
    flipped = NeuralSDF(NeuralSDFConfig(init_radius=0.7, inside_out=True))
    x = torch.cat([torch.zeros(1, 3), unit_dirs(100) * torch.rand(100, 1)])
    with torch.no_grad():
        a, b = normal.sdf(x), flipped.sdf(x)
    torch.testing.assert_close(b, -a, atol=1e-6, rtol=0)
    assert b[0] > 0.3  # positive at the centre: a room seen from inside is free space there
    s_far = flipped.sdf(unit_dirs(50, seed=1) * 0.99)
    assert (s_far < 0).float().mean() > 0.95


# -- finite-difference gradients ------------------------------------------------------------------
def test_tetrahedral_gradient_of_an_analytic_sphere() -> None:
    sphere = Sphere(0.6, (0.1, -0.2, 0.05))
    c = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    x = c + unit_dirs(300, dtype=torch.float64) * (0.2 + torch.rand(300, 1, dtype=torch.float64))
    grad, mean = tetrahedral_gradient(sphere.sdf, x, h=1e-4)
    true = torch.nn.functional.normalize(x - c, dim=-1)
    assert grad.shape == (300, 3) and mean.shape == (300,)
    assert (grad - true).norm(dim=-1).max() < 1e-3
    # The mean of the four samples is the SDF at x to second order.
    assert (mean - sphere.sdf(x)).abs().max() < 1e-6
    # Differentiable: the training losses back-propagate through it.
    xr = x.clone().requires_grad_(True)
    g2, _ = tetrahedral_gradient(sphere.sdf, xr, h=1e-3)
    g2.norm(dim=-1).sum().backward()
    assert xr.grad is not None and torch.isfinite(xr.grad).all()


def test_tetrahedral_gradient_closed_forms() -> None:
    # Exact for linear functions at any step: a box face's SDF is linear near its centre.
    box = Box((0.5, 0.4, 0.3))
    x = torch.tensor([[0.7, 0.0, 0.0], [0.0, -0.55, 0.05], [0.02, 0.0, 0.5]], dtype=torch.float64)
    grad, mean = tetrahedral_gradient(box.sdf, x, h=0.05)
    expect = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(grad, expect, atol=1e-12, rtol=0)
    torch.testing.assert_close(mean, torch.tensor([0.2, 0.15, 0.2], dtype=torch.float64))
    # The 4-point stencil is first-order: for f = x y (gradient (y, x, 0)) it returns
    # (y, x, h), since sum_k k_x k_y k_z = 4 over the tetrahedron's vertices.
    pts = torch.tensor([[0.3, -0.7, 2.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    h = 0.01
    grad, mean = tetrahedral_gradient(lambda p: p[:, 0] * p[:, 1], pts, h)
    expect = torch.tensor([[-0.7, 0.3, h], [2.0, 1.0, h]], dtype=torch.float64)
    torch.testing.assert_close(grad, expect, atol=1e-12, rtol=0)
    # The mean of xy over the stencil: xy + h^2 mean(k_x k_y) = xy - 0 (k_x k_y sums to 0).
    torch.testing.assert_close(mean, pts[:, 0] * pts[:, 1], atol=1e-12, rtol=0)


@pytest.mark.parametrize("encoding", ["dense", "hash"])
def test_autograd_gradient_matches_finite_differences(encoding: str) -> None:
    cfg = NeuralSDFConfig(**{**SMALL.to_json(), "encoding": encoding, "hash_table_size_log2": 10})
    torch.manual_seed(0)
    bounds = torch.tensor([[-1.0, -0.6, -0.4], [1.0, 0.6, 0.8]])
    field = randomised(NeuralSDF(cfg, bounds=bounds), std=0.5).double()
    g = torch.Generator().manual_seed(1)
    x = (bounds[0] + torch.rand(64, 3, generator=g) * (bounds[1] - bounds[0])).double() * 0.9
    s, grad = field.sdf_and_gradient(x)
    assert grad.shape == (64, 3) and s.shape == (64,)
    h = 1e-6
    eye = torch.eye(3, dtype=torch.float64)
    with torch.no_grad():
        fd = torch.stack(
            [(field.sdf(x + h * eye[i]) - field.sdf(x - h * eye[i])) / (2 * h) for i in range(3)],
            -1,
        )
        torch.testing.assert_close(s, field.sdf(x), atol=1e-12, rtol=0)
    assert grad.abs().max() > 0.1  # the gradient is not trivially zero
    torch.testing.assert_close(grad, fd, atol=1e-5, rtol=1e-4)
    # Under no_grad too, and normal() is the unit gradient.
    with torch.no_grad():
        torch.testing.assert_close(field.gradient(x), grad)
        torch.testing.assert_close(field.normal(x), torch.nn.functional.normalize(grad, dim=-1))


# -- heads and encodings --------------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ["dense", "hash"])
def test_forward_backward_and_output_dims(encoding: str) -> None:
    cfg = NeuralSDFConfig(**{**SMALL.to_json(), "encoding": encoding, "hash_table_size_log2": 9})
    torch.manual_seed(0)
    field = randomised(NeuralSDF(cfg))
    assert field.encoding.output_dim == cfg.levels * cfg.features_per_level
    assert field.sdf_layers[0].in_features == 3 + cfg.levels * cfg.features_per_level
    x = torch.rand(257, 3) * 2 - 1
    s, feat = field.sdf_and_features(x)
    assert s.shape == (257,) and feat.shape == (257, cfg.geo_feature_dim)
    c = field.color(x)
    c = c.detach()
    assert c.shape == (257, 3) and float(c.min()) >= 0.0 and float(c.max()) <= 1.0
    assert c.std(0).min() > 1e-3  # not a constant
    assert field(x).shape == (257,)  # forward() is the SDF
    loss = (
        s.square().mean()
        + field.color_from(feat, torch.nn.functional.normalize(x, dim=-1), None).mean()
    )
    loss.backward()
    grads = {n: p.grad for n, p in field.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values())
    enc = [n for n in grads if n.startswith("encoding.")]
    assert len(enc) == cfg.levels
    assert all(grads[n].abs().sum() > 0 for n in enc), "every grid level must receive gradient"
    assert grads["color_net.4.weight"].abs().sum() > 0


def test_grid_features_reach_the_colour_head_directly() -> None:
    """With ``color_grid_features`` the colour head reads the grid features themselves: a
    colour loss moves the grids even with the SDF MLP's feature outputs cut off; without it,
    it does not."""
    x = torch.rand(257, 3) * 2 - 1
    normals = torch.nn.functional.normalize(x, dim=-1)
    for flag in (True, False):
        cfg = NeuralSDFConfig(**{**SMALL.to_json(), "color_grid_features": flag})
        torch.manual_seed(0)
        field = randomised(NeuralSDF(cfg))
        enc_dim = cfg.levels * cfg.features_per_level
        assert field.color_net[0].in_features == cfg.geo_feature_dim + 3 + (enc_dim if flag else 0)
        with torch.no_grad():  # the SDF MLP's feature outputs: constant 0
            field.sdf_layers[-1].weight[1:].zero_()
            field.sdf_layers[-1].bias[1:].zero_()
        _, feat = field.sdf_and_features(x)
        assert feat.shape == (257, cfg.geo_feature_dim + (enc_dim if flag else 0))
        if flag:
            assert torch.equal(feat[:, cfg.geo_feature_dim:], field.encoding(field.box_coordinates(x)))
        field.color_from(feat, normals, None).square().mean().backward()
        moved = sum(float(p.grad.abs().sum()) for n, p in field.named_parameters()
                    if n.startswith("encoding.") and p.grad is not None)
        assert (moved > 0) == flag


def test_hash_encoding_hashes_fine_levels_only() -> None:
    enc = HashGridEncoding(
        torch.tensor([2.0, 2.0, 2.0]),
        levels=3,
        features=2,
        base_resolution=4,
        finest_resolution=16,
        table_size_log2=8,
    )
    # (4+1)^3 = 125 vertices fit in 256 entries; (8+1)^3 and (16+1)^3 do not.
    assert [t.shape[0] for t in enc.tables] == [125, 256, 256]
    out = enc(torch.rand(100, 3) * 2 - 1)
    assert out.shape == (100, 6) and torch.isfinite(out).all()


def test_color_is_view_dependent_only_when_configured() -> None:
    x = torch.rand(50, 3) - 0.5
    d1, d2 = unit_dirs(50, 1), unit_dirs(50, 2)
    torch.manual_seed(0)
    plain = randomised(NeuralSDF(SMALL))
    torch.testing.assert_close(plain.color(x, d1), plain.color(x, d2), atol=0, rtol=0)
    torch.manual_seed(0)
    viewdep = randomised(NeuralSDF(NeuralSDFConfig(**{**SMALL.to_json(), "view_dependent": True})))
    assert (viewdep.color(x, d1) - viewdep.color(x, d2)).abs().max() > 1e-3
    assert viewdep.color_net[0].in_features == SMALL.geo_feature_dim + 6


def test_dense_grid_reproduces_a_linear_function() -> None:
    """Trilinear interpolation is exact for linear functions: storing each vertex's box
    coordinate as features must give back the query coordinate, x along W, y along H, z along D."""
    extent = torch.tensor([2.0, 1.0, 0.5])
    enc = DenseGridEncoding(extent, levels=2, features=3, base_resolution=5, finest_resolution=9)
    for res, grid in zip(enc.resolutions, enc.grids):
        nx, ny, nz = grid_shape(res, extent)
        assert grid.shape == (1, 3, nz, ny, nx)
        zz, yy, xx = torch.meshgrid(
            torch.linspace(-1, 1, nz),
            torch.linspace(-1, 1, ny),
            torch.linspace(-1, 1, nx),
            indexing="ij",
        )
        with torch.no_grad():
            grid.copy_(torch.stack([xx, yy, zz])[None])
    u = torch.rand(200, 3) * 2 - 1
    out = enc(u)
    torch.testing.assert_close(out, torch.cat([u, u], dim=-1), atol=1e-5, rtol=0)


def test_hash_grid_dense_levels_reproduce_a_linear_function() -> None:
    extent = torch.tensor([2.0, 1.0, 1.5])
    enc = HashGridEncoding(
        extent, levels=2, features=3, base_resolution=4, finest_resolution=8, table_size_log2=16
    )
    for shape, table in zip(enc.shapes, enc.tables):
        nx, ny, nz = shape
        idx = torch.arange(table.shape[0])
        cx, cy, cz = idx % (nx + 1), (idx // (nx + 1)) % (ny + 1), idx // ((nx + 1) * (ny + 1))
        with torch.no_grad():
            table.copy_(torch.stack([cx / nx, cy / ny, cz / nz], -1) * 2 - 1)
    u = torch.rand(200, 3) * 2 - 1
    torch.testing.assert_close(enc(u), torch.cat([u, u], dim=-1), atol=1e-5, rtol=0)


def test_level_resolutions_are_geometric() -> None:
    assert level_resolutions(4, 16, 128) == [16, 32, 64, 128]
    assert level_resolutions(1, 16, 48) == [48]
    for bad in [(0, 16, 32), (3, 1, 32), (3, 64, 32)]:
        with pytest.raises(ValueError):
            level_resolutions(*bad)
    # Cubic cells: an anisotropic box gets proportionally fewer cells on its short axes.
    assert grid_shape(64, torch.tensor([4.0, 2.0, 0.1])) == (64, 32, 2)


# -- configuration ----------------------------------------------------------------------------
def test_config_json_round_trip_and_rejections() -> None:
    cfg = NeuralSDFConfig(encoding="hash", levels=5, init_radius=0.8, inside_out=True)
    assert NeuralSDFConfig.from_json(cfg.to_json()) == cfg
    assert NeuralSDFConfig.from_json({}) == NeuralSDFConfig()
    with pytest.raises(ValueError, match=r"unknown architecture keys \['depth', 'width'\]"):
        NeuralSDFConfig.from_json({**cfg.to_json(), "width": 3, "depth": 2})
    with pytest.raises(ValueError, match="unknown encoding 'fourier'"):
        NeuralSDFConfig.from_json({"encoding": "fourier"})
    with pytest.raises(ValueError, match="unknown encoding"):
        NeuralSDF(NeuralSDFConfig(encoding="tcnn"))


def test_field_frame_defaults_and_validation() -> None:
    field = NeuralSDF(SMALL)
    torch.testing.assert_close(field.bounds, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    assert field.to_world.dtype == torch.float64 and torch.equal(
        field.to_world, torch.eye(4, dtype=torch.float64)
    )
    assert field.diagonal == pytest.approx(2 * math.sqrt(3))
    with pytest.raises(ValueError, match="bounds"):
        NeuralSDF(SMALL, bounds=torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]]))
    with pytest.raises(ValueError, match="to_world"):
        NeuralSDF(SMALL, to_world=torch.eye(3))
    # box_coordinates maps the bounds onto [-1, 1]^3.
    f2 = NeuralSDF(SMALL, bounds=torch.tensor([[0.0, -2.0, 1.0], [4.0, 2.0, 2.0]]))
    corners = torch.tensor([[0.0, -2.0, 1.0], [4.0, 2.0, 2.0], [2.0, 0.0, 1.5]])
    torch.testing.assert_close(
        f2.box_coordinates(corners), torch.tensor([[-1.0] * 3, [1.0] * 3, [0.0] * 3])
    )
