"""Barron's adaptive robust loss: closed forms, normalisation, gradients, learning the shape."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import quad
from scipy.special import k1

from regnf.registration.robust_loss import (
    AdaptiveRobustLoss,
    general_rho,
    log_partition,
    partition_numeric,
    partition_table,
    robust_nll,
)


def _direct_partition(alpha: float) -> float:
    """Z(alpha) straight from the definition, written independently of the module."""
    def f(x: float) -> float:
        if alpha == 0:
            return 1.0 / (0.5 * x * x + 1.0)
        b = abs(alpha - 2.0)
        return math.exp(-(b / alpha) * ((x * x / b + 1.0) ** (alpha / 2.0) - 1.0))

    return 2.0 * quad(f, 0.0, np.inf, epsabs=1e-12, epsrel=1e-11, limit=400)[0]


def test_partition_closed_forms() -> None:
    # alpha = 0: integral of 1 / (x^2 / 2 + 1) = pi sqrt(2); alpha = 2: Gaussian sqrt(2 pi);
    # alpha = 1: x = sinh(u) turns it into 2 e K_1(1).
    for alpha, z in ((0.0, math.pi * math.sqrt(2.0)), (1.0, 2.0 * math.e * k1(1.0)),
                     (2.0, math.sqrt(2.0 * math.pi))):
        assert partition_numeric(alpha) == pytest.approx(z, rel=1e-9)
        got = float(log_partition(torch.tensor(alpha, dtype=torch.float64)))
        assert got == pytest.approx(math.log(z), abs=1e-8)


@pytest.mark.parametrize("alpha", [1e-6, 0.0037, 0.21, 0.5, 0.77, 0.999, 1.33, 1.95, 1.9999])
def test_log_partition_matches_direct_integration(alpha: float) -> None:
    got = float(log_partition(torch.tensor(alpha, dtype=torch.float64)))
    assert got == pytest.approx(math.log(_direct_partition(alpha)), abs=1e-7)


def test_partition_table_matches_quadrature() -> None:
    # The vectorised rule against quad, shape by shape, at both ends and in between.
    alphas = np.array([0.0, 1e-9, 1e-6, 0.0037, 0.5, 1.0, 1.5, 1.99, 2.0 - 1e-9, 2.0])
    want = np.array([partition_numeric(float(a)) for a in alphas])
    np.testing.assert_allclose(partition_table(alphas), want, rtol=1e-10)
    with pytest.raises(ValueError, match="alpha in"):
        partition_table(np.array([0.5, 2.5]))


def test_rho_hand_values() -> None:
    x = torch.tensor([0.0, 1.0, 2.0, -3.0], dtype=torch.float64)
    # alpha = 1, c = 1: sqrt(x^2 + 1) - 1.
    assert torch.allclose(general_rho(x, 1.0, 1.0), torch.sqrt(x**2 + 1) - 1, atol=1e-12)
    # alpha = 2, c = 2: x^2 / 8.
    assert torch.allclose(general_rho(x, 2.0, 2.0), x**2 / 8, atol=1e-12)
    # alpha = 0, c = 1: log(x^2 / 2 + 1).
    assert torch.allclose(general_rho(x, 0.0, 1.0), torch.log(0.5 * x**2 + 1), atol=1e-12)
    # alpha = 0.5, c = 0.5, x = 1: (1.5 / 0.5) ((4 / 1.5 + 1)^0.25 - 1) = 3 ((11/3)^0.25 - 1).
    v = float(general_rho(torch.tensor([1.0], dtype=torch.float64), 0.5, 0.5))
    assert v == pytest.approx(3.0 * ((11.0 / 3.0) ** 0.25 - 1.0), rel=1e-12)
    # The general formula is continuous into both limits.
    near0 = general_rho(x, 1e-6, 1.0)
    near2 = general_rho(x, 2.0 - 1e-6, 1.0)
    assert torch.allclose(near0, general_rho(x, 0.0, 1.0), atol=1e-4)
    assert torch.allclose(near2, general_rho(x, 2.0, 1.0), atol=1e-4)


@pytest.mark.parametrize(("alpha", "c"), [(0.05, 1.0), (0.5, 0.3), (1.0, 2.0), (1.7, 0.05)])
def test_nll_is_a_normalised_density(alpha: float, c: float) -> None:
    def p(x: float) -> float:
        return math.exp(-float(robust_nll(torch.tensor([x], dtype=torch.float64), alpha, c)))

    total = 2.0 * quad(p, 0.0, np.inf, limit=400, epsabs=1e-11)[0]
    assert total == pytest.approx(1.0, abs=1e-6)


def test_gradients_are_finite_everywhere() -> None:
    loss = AdaptiveRobustLoss(groups=1, alpha_lo=0.0, alpha_hi=2.0)
    x = torch.tensor([0.0, 1e-8, 1e-3, 0.3, 5.0, 1e4], requires_grad=True)
    for latent in (-30.0, -3.0, 0.0, 3.0, 30.0):  # alpha at (or numerically at) 0, mid, 2
        with torch.no_grad():
            loss.latent_alpha.fill_(latent)
        loss.zero_grad()
        x.grad = None
        out = loss(x)
        assert bool(torch.isfinite(out).all())
        out.sum().backward()
        for g in (x.grad, loss.latent_alpha.grad, loss.latent_scale.grad):
            assert bool(torch.isfinite(g).all())
    # d log Z / d alpha from the spline equals a finite difference of the quadrature.
    a = torch.tensor(0.6, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(log_partition(a), a)
    fd = (math.log(_direct_partition(0.601)) - math.log(_direct_partition(0.599))) / 0.002
    assert float(g) == pytest.approx(fd, rel=1e-4)


def test_parameter_ranges_and_init() -> None:
    loss = AdaptiveRobustLoss(groups=3, alpha_lo=1e-6, alpha_hi=1.0, scale_init=1.0)
    assert torch.allclose(loss.alpha, torch.full((3,), 0.5 * (1.0 + 1e-6)))
    assert torch.allclose(loss.scale, torch.ones(3))
    with torch.no_grad():
        loss.latent_alpha.copy_(torch.tensor([-100.0, 0.0, 100.0]))
        loss.latent_scale.fill_(-100.0)
    assert bool(((loss.alpha >= 1e-6) & (loss.alpha <= 1.0)).all())
    assert bool((loss.scale >= 1e-5).all())
    r = torch.tensor([0.1, 0.2, 0.3])
    per = loss(r, torch.tensor([0, 1, 2]))
    assert per.shape == (3,)
    with pytest.raises(ValueError, match="group"):
        loss(r)
    with pytest.raises(ValueError, match="alpha_lo"):
        AdaptiveRobustLoss(alpha_lo=-0.1)
    with pytest.raises(ValueError, match="alpha_init"):
        AdaptiveRobustLoss(alpha_init=1.5)


def _fit_alpha(samples: torch.Tensor, steps: int = 400) -> tuple[float, float]:
    loss = AdaptiveRobustLoss(groups=1, alpha_lo=0.0, alpha_hi=2.0)
    opt = torch.optim.Adam(loss.parameters(), lr=0.05)
    for _ in range(steps):
        opt.zero_grad()
        loss(samples).mean().backward()
        opt.step()
    return float(loss.alpha.detach()[0]), float(loss.scale.detach()[0])


def test_heavy_tails_learn_a_smaller_alpha() -> None:
    gen = torch.Generator().manual_seed(0)
    gauss = 0.3 * torch.randn(4000, generator=gen)
    # Standard Cauchy by inverse CDF, from the same seeded generator.
    cauchy = 0.3 * torch.tan(math.pi * (torch.rand(4000, generator=gen) - 0.5))
    a_gauss, c_gauss = _fit_alpha(gauss)
    a_cauchy, _ = _fit_alpha(cauchy)
    assert a_gauss > 1.5  # Gaussian data: close to the L2 end (alpha = 2)
    assert a_cauchy < 0.5  # Cauchy data: close to the Cauchy-like end (alpha = 0)
    # alpha = 2 is a Gaussian with sigma = c: the scale is learnt as the standard deviation.
    assert c_gauss == pytest.approx(0.3, rel=0.15)
