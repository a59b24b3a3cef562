"""Robust least squares for the refinement: Barron's kernel as IRLS weights, the kernel's shape
and scale fitted to the residuals, and the damped normal equations (Levenberg-Marquardt).

The refinement's objective is a sum of robust terms ``sum_i a_i rho(x_i; alpha, c)`` over
residuals ``x_i`` (library reference lengths) plus squared point distances. Iteratively
reweighted least squares replaces each robust term by the quadratic with the same value and
slope at the current residual: ``rho(x + d) ~ rho(x) + W x d + W d^2 / 2`` with
``W = rho'(x) / x``, which for Barron's loss is

    W(x) = (1 / c^2) ((x / c)^2 / |alpha - 2| + 1)^(alpha / 2 - 1),

non-increasing in |x| for alpha <= 2, so the quadratic lies above the loss (a majoriser):
safe steps, but only linear convergence. The loss's own curvature ``max(rho''(x), 0)``
(:func:`barron_curvature`) gives Newton's faster steps; the refinement uses it, and the
majoriser after a step that failed. Either way one step solves a damped 8 x 8 system.

The kernel's (alpha, c) minimise the negative log-likelihood of the residuals (the adaptive
loss, :mod:`regnf.registration.robust_loss`). With the residuals fixed that is a two-parameter
problem; it is solved exactly on a grid, evaluated on a log-spaced histogram of the residuals
(so its cost does not grow with the number of samples).
"""

from __future__ import annotations

import torch

from regnf.registration.robust_loss import general_rho, log_partition

HISTOGRAM_DECADES = (-8.0, 1.0)
"""log10 range of |residual| (reference lengths) of the kernel fit's histogram; smaller values
fall in the first bin, larger ones in the last."""
HISTOGRAM_BINS = 180
"""Bins of that histogram: 0.05 decades (12 % in the residual) each."""
ALPHA_FRACTIONS = (0.001, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.99)
"""The kernel shapes tried, as fractions of the allowed range (alpha_lo, alpha_hi)."""
SCALE_DECADES = (-4.0, -0.5)
"""log10 range of the kernel scales tried, reference lengths."""
SCALE_STEPS = 36
"""Scales tried (0.1 decade apart)."""


def barron_weight(x: torch.Tensor, alpha: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """IRLS weights ``rho'(x) / x`` of Barron's loss (elementwise, broadcasting).

    Parameters
    ----------
    x : (n,) float
        Residuals.
    alpha : (n,) float
        Shapes in [0, 2].
    scale : (n,) float
        Scales c > 0.

    Returns
    -------
    (n,) float, positive.
    """
    beta = (alpha - 2.0).abs().clamp(min=1e-7)
    return torch.pow((x / scale) ** 2 / beta + 1.0, 0.5 * alpha - 1.0) / scale**2


def barron_curvature(x: torch.Tensor, alpha: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``max(rho''(x), 0)`` of Barron's loss (elementwise, broadcasting): the Newton weight.

    ``rho''(x) = (1 / c^2) u^(alpha / 2 - 2) (1 - z^2 (1 - 1 / |alpha - 2|))`` with ``z = x / c``
    and ``u = z^2 / |alpha - 2| + 1``; negative beyond the kernel's inflection, where the term
    is no longer convex, and clamped to 0 there.

    Parameters
    ----------
    x, alpha, scale : (n,) float
        As :func:`barron_weight`.

    Returns
    -------
    (n,) float, non-negative.
    """
    beta = (alpha - 2.0).abs().clamp(min=1e-7)
    z2 = (x / scale) ** 2
    u = z2 / beta + 1.0
    return (torch.pow(u, 0.5 * alpha - 2.0) * (1.0 - z2 * (1.0 - 1.0 / beta))).clamp(min=0.0) / scale**2


def fit_kernel(
    x: torch.Tensor, weight: torch.Tensor, group: torch.Tensor, k: int, alpha_lo: float, alpha_hi: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per group, the (alpha, c) of the grid that minimise ``sum_i w_i nll(x_i; alpha, c)``.

    Parameters
    ----------
    x : (n,) float
        Residuals, reference lengths.
    weight : (n,) float
        Non-negative weights ``w_i``.
    group : (n,) long
        Group in [0, k) of each residual.
    k : int
        Number of groups.
    alpha_lo, alpha_hi : float
        Allowed shape range; the grid lies strictly inside it.

    Returns
    -------
    alpha, scale : (k,) float64 each
    """
    dev = x.device
    f64 = {"device": dev, "dtype": torch.float64}
    lo, hi = HISTOGRAM_DECADES
    logx = torch.log10(x.detach().double().abs().clamp(min=10.0**lo))
    b = ((logx - lo) / (hi - lo) * HISTOGRAM_BINS).long().clamp(0, HISTOGRAM_BINS - 1)
    hist = torch.zeros(k * HISTOGRAM_BINS, **f64).index_add_(
        0, group * HISTOGRAM_BINS + b, weight.detach().double()).view(k, HISTOGRAM_BINS)
    centres = 10.0 ** (lo + (torch.arange(HISTOGRAM_BINS, **f64) + 0.5) * (hi - lo) / HISTOGRAM_BINS)
    alphas = alpha_lo + (alpha_hi - alpha_lo) * torch.tensor(ALPHA_FRACTIONS, **f64)
    scales = torch.logspace(SCALE_DECADES[0], SCALE_DECADES[1], SCALE_STEPS, **f64)
    a, c = alphas[:, None, None], scales[None, :, None]
    nll = general_rho(centres[None, None, :], a, c) + torch.log(c) + log_partition(a)  # (na, nc, bins)
    total = torch.einsum("kb,acb->kac", hist, nll).reshape(k, -1)
    best = total.argmin(dim=1)
    return alphas[best // SCALE_STEPS], scales[best % SCALE_STEPS]


def segment_normal_equations(
    J: torch.Tensor, x: torch.Tensor, a: torch.Tensor, group: torch.Tensor, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``H = sum_i a_i J_i J_i^T`` and ``g = sum_i a_i x_i J_i`` per group.

    Parameters
    ----------
    J : (n, p) float64
        Jacobian rows of the residuals.
    x : (n,) float64
        Residuals.
    a : (n,) float64
        Per-residual weights.
    group : (n,) long
        Group in [0, k) of each residual.
    k : int

    Returns
    -------
    H : (k, p, p) float64
    g : (k, p) float64
    """
    aJ = a[:, None] * J
    return _gram(aJ, J, group, k), J.new_zeros(k, J.shape[1]).index_add_(0, group, aJ * x[:, None])


def segment_gram(J: torch.Tensor, a: torch.Tensor, group: torch.Tensor, k: int) -> torch.Tensor:
    """``H = sum_i a_i J_i J_i^T`` per group alone: (k, p, p) from J (n, p), a (n,), group (n,)."""
    return _gram(a[:, None] * J, J, group, k)


def segment_mean(values: torch.Tensor, group: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """(k,) mean of ``values`` (n,) per group (n,) long, ``counts`` (k,) float."""
    out = values.new_zeros(counts.shape[0])
    return out.index_add(0, group, values) / counts.clamp(min=1)


def segment_sum(values: torch.Tensor, group: torch.Tensor, k: int) -> torch.Tensor:
    """(k,) sum of ``values`` (n,) per group (n,) long."""
    return values.new_zeros(k).index_add(0, group, values)


def _gram(aJ: torch.Tensor, J: torch.Tensor, group: torch.Tensor, k: int) -> torch.Tensor:
    p = J.shape[1]
    H = J.new_zeros(k, p * p).index_add_(0, group, (aJ[:, :, None] * J[:, None, :]).reshape(-1, p * p))
    return H.view(k, p, p)


def damped_step(H: torch.Tensor, g: torch.Tensor, damping: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """Levenberg-Marquardt step ``-(H + mu diag(H))^-1 g`` for each of k problems.

    Parameters
    ----------
    H : (k, p, p) float64
        Gauss-Newton matrices.
    g : (k, p) float64
        Gradients.
    damping : (k,) float64
        mu per problem.
    free : (p,) or (k, p) bool
        Parameters that may move (for all problems, or per problem); the others get a zero step.

    Returns
    -------
    (k, p) float64
    """
    fixed = (~free).expand_as(g).to(H.dtype)
    keep = 1.0 - fixed
    H = H * keep[:, :, None] * keep[:, None, :]
    g = g * keep
    diag = H.diagonal(dim1=1, dim2=2)
    # Marquardt's scaling by the diagonal, floored so that a parameter the data barely
    # constrain still gets a finite step.
    floor = 1e-9 * diag.amax(dim=1, keepdim=True).clamp(min=1e-30)
    scaled = diag.clamp(min=0.0) + floor
    A = H + torch.diag_embed(damping[:, None] * scaled + fixed)
    step = torch.linalg.solve(A, -g[..., None])[..., 0]
    return torch.where(torch.isfinite(step), step, torch.zeros_like(step))

