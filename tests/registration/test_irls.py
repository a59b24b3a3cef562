"""Robust least-squares pieces of the refinement against independent truths."""

from __future__ import annotations

import math

import torch

from regnf.registration.irls import (
    ALPHA_FRACTIONS,
    SCALE_DECADES,
    SCALE_STEPS,
    barron_curvature,
    barron_weight,
    damped_step,
    fit_kernel,
    segment_normal_equations,
)
from regnf.registration.robust_loss import general_rho, robust_nll


def test_weights_are_the_loss_slope_over_the_residual() -> None:
    """W(x) = rho'(x) / x, against autograd of Barron's loss, for several shapes and scales."""
    x = torch.linspace(-0.3, 0.3, 241, dtype=torch.float64)
    x = x[x.abs() > 1e-6].requires_grad_(True)
    for alpha in (1e-6, 0.3, 1.0, 1.7):
        for c in (0.003, 0.05):
            (slope,) = torch.autograd.grad(general_rho(x, alpha, c).sum(), x)
            a = torch.full_like(x, alpha)
            W = barron_weight(x.detach(), a, torch.full_like(x, c))
            torch.testing.assert_close(W * x.detach(), slope, rtol=1e-6, atol=1e-9)
            # Non-increasing in |x| for alpha <= 2: the IRLS quadratic majorises the loss.
            pos = x.detach() > 0
            assert bool((W[pos][1:] <= W[pos][:-1] * (1 + 1e-12)).all())


def test_curvature_is_the_loss_second_derivative_clamped_at_zero() -> None:
    x = torch.linspace(-0.3, 0.3, 241, dtype=torch.float64).requires_grad_(True)
    for alpha in (1e-6, 0.3, 1.0, 1.7):
        for c in (0.003, 0.05):
            (slope,) = torch.autograd.grad(general_rho(x, alpha, c).sum(), x, create_graph=True)
            (second,) = torch.autograd.grad(slope.sum(), x)
            got = barron_curvature(x.detach(), torch.full_like(x, alpha), torch.full_like(x, c))
            torch.testing.assert_close(got, second.clamp(min=0.0), rtol=1e-6, atol=1e-9)
            # Never above the reweighting's curvature: the majoriser is the cautious step.
            W = barron_weight(x.detach(), torch.full_like(x, alpha), torch.full_like(x, c))
            assert bool((got <= W * (1 + 1e-12)).all())


def test_kernel_fit_finds_the_generating_scale_and_shape() -> None:
    """Gaussian residuals give the least robust shape on offer and c near sigma; residuals
    with 30 % gross outliers give a robust shape and c still near the inliers' sigma."""
    gen = torch.Generator().manual_seed(0)
    sigma = 0.004
    clean = sigma * torch.randn(20000, generator=gen, dtype=torch.float64)
    outliers = 0.3 * (torch.rand(8000, generator=gen, dtype=torch.float64) - 0.5)
    dirty = torch.cat([clean[:12000], outliers])
    x = torch.cat([clean, dirty])
    group = torch.cat([torch.zeros(20000, dtype=torch.long), torch.ones(20000, dtype=torch.long)])
    w = torch.full((40000,), 1.0 / 20000, dtype=torch.float64)
    alpha, c = fit_kernel(x, w, group, 2, 0.0, 2.0)
    step = 10 ** ((SCALE_DECADES[1] - SCALE_DECADES[0]) / (SCALE_STEPS - 1))
    assert float(alpha[0]) >= 2.0 * ALPHA_FRACTIONS[-2]  # Gaussian: the top of the grid
    assert abs(math.log(float(c[0]) / sigma)) <= math.log(step)
    assert float(alpha[1]) <= 1.0
    assert abs(math.log(float(c[1]) / sigma)) <= 2 * math.log(step)
    # The histogram approximation picks (nearly) the best pair of the grid on the raw data.
    alphas = 2.0 * torch.tensor(ALPHA_FRACTIONS, dtype=torch.float64)
    scales = torch.logspace(*SCALE_DECADES, SCALE_STEPS, dtype=torch.float64)
    raw = torch.stack([torch.stack([robust_nll(dirty, a, s).mean() for s in scales]) for a in alphas])
    chosen = robust_nll(dirty, alpha[1], c[1]).mean()
    assert float(chosen) <= float(raw.min()) + 1e-3 * abs(float(raw.min()))


def test_damped_step_solves_the_normal_equations() -> None:
    gen = torch.Generator().manual_seed(1)
    J = torch.randn(300, 8, generator=gen, dtype=torch.float64)
    x = torch.randn(300, generator=gen, dtype=torch.float64)
    a = torch.rand(300, generator=gen, dtype=torch.float64)
    group = torch.arange(300) % 2
    H, g = segment_normal_equations(J, x, a, group, 2)
    for k in range(2):
        Jk, xk, ak = J[group == k], x[group == k], a[group == k]
        torch.testing.assert_close(H[k], Jk.T @ (ak[:, None] * Jk))
        torch.testing.assert_close(g[k], Jk.T @ (ak * xk))
    free = torch.ones(8, dtype=torch.bool)
    step = damped_step(H, g, torch.full((2,), 1e-12, dtype=torch.float64), free)
    torch.testing.assert_close(step, -torch.linalg.solve(H, g[..., None])[..., 0], rtol=1e-6, atol=1e-9)
    # A fixed parameter does not move; the others solve the reduced system.
    free[3] = False
    step = damped_step(H, g, torch.full((2,), 1e-12, dtype=torch.float64), free)
    assert bool((step[:, 3] == 0).all())
    keep = free.nonzero()[:, 0]
    Hr = H[:, keep][:, :, keep]
    torch.testing.assert_close(step[:, keep], -torch.linalg.solve(Hr, g[:, keep, None])[..., 0],
                               rtol=1e-6, atol=1e-9)
    # Damping shortens the step.
    damped = damped_step(H, g, torch.full((2,), 10.0, dtype=torch.float64), free)
    assert bool((damped.norm(dim=1) < step.norm(dim=1)).all())
