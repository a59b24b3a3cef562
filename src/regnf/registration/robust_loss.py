"""Barron's general adaptive robust loss, as a negative log-likelihood with learnt shape and scale.

J. T. Barron, "A General and Adaptive Robust Loss Function", CVPR 2019. The general loss

    rho(x, alpha, c) = |alpha - 2| / alpha * (((x / c)^2 / |alpha - 2| + 1)^(alpha / 2) - 1)

(with its limits ``log(x^2 / (2 c^2) + 1)`` at ``alpha = 0`` and ``x^2 / (2 c^2)`` at
``alpha = 2``) is turned into a density ``p(x) = exp(-rho(x, alpha, c)) / (c Z(alpha))`` whose
negative log-likelihood

    nll(x; alpha, c) = rho(x, alpha, c) + log c + log Z(alpha)

can be minimised over ``alpha`` and ``c`` too: without the ``log c + log Z`` terms the loss
would always prefer the most robust shape and the largest scale. Reg-NF (docs/design.md section 1.5)
learns one (alpha, c) pair shared by both residual sets, alpha in (0, 1], c initialised to 1.

``Z(alpha) = integral over the real line of exp(-rho(x, alpha, 1))`` has no closed form for
general alpha (``pi sqrt(2)`` at 0, ``2 e K_1(1)`` at 1, ``sqrt(2 pi)`` at 2). It is integrated
numerically once, at first use, at knots over [0, 2] (:func:`partition_table`: a double-exponential
quadrature of every knot at once, far faster than ``scipy.integrate.quad`` knot by knot, which
stays the tests' reference; docs/decisions/implementation-speed.md), and ``log Z`` is
interpolated by a cubic spline evaluated in torch: the spline is
C2, so the loss is smooth and differentiable in alpha. ``log Z`` is not analytic at the ends
(an ``eps log eps`` term at alpha = 2 - eps, a weaker one at 0), so the knots are graded there
(spacing proportional to the distance to the end) and uniform in the middle; the spline then
agrees with direct integration to about 2e-8 everywhere (tested at off-knot alphas).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import torch

from regnf.core.errors import RegnfError

ALPHA_TABLE_MAX = 2.0
"""Largest shape the log-partition table covers (the table spans [0, ALPHA_TABLE_MAX])."""

TABLE_MAX_SPACING = 1.0 / 32.0
"""Largest knot spacing of the log-partition spline (in the middle of the range)."""

TABLE_GRADING = 0.1
"""Near alpha = 0 and alpha = 2 the knot spacing is this fraction of the distance to the end."""

TABLE_END_GAP = 1e-9
"""Closest knot to each end (besides the end itself)."""

_SAFE_EPS = 1e-7
"""Floor on alpha and |alpha - 2| in the general formula: keeps both limits finite (and their
gradients NaN-free under ``torch.where``), below float32 resolution of the loss."""


def _rho_numpy(x: np.ndarray | float, alpha: np.ndarray | float) -> np.ndarray:
    """Barron's rho at scale 1 in float64 numpy, with the alpha = 0 and alpha = 2 limits;
    ``x`` and ``alpha`` broadcast (a row per shape: ``x[None, :]``, ``alpha[:, None]``)."""
    x2 = np.square(np.asarray(x, dtype=np.float64))
    a = np.asarray(alpha, dtype=np.float64)
    beta = np.abs(a - 2.0)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        general = beta / np.where(a == 0.0, 1.0, a) * np.expm1(
            0.5 * a * np.log1p(x2 / np.where(beta == 0.0, 1.0, beta)))
    return np.where(a == 0.0, np.log1p(0.5 * x2), np.where(a == 2.0, 0.5 * x2, general))


def partition_numeric(alpha: float) -> float:
    """``Z(alpha)``: the integral of ``exp(-rho(x, alpha, 1))`` over the real line, by quadrature.

    Parameters
    ----------
    alpha : float
        Shape in [0, 2] (for alpha < 0 the integral diverges).

    Returns
    -------
    float
    """
    from scipy.integrate import quad

    if not 0.0 <= alpha <= ALPHA_TABLE_MAX:
        raise RegnfError(f"the partition function is tabulated for alpha in [0, 2], got {alpha}")
    # The integrand is even; for alpha -> 0 its tail decays only like 2 / x^2, which quad's
    # mapping of [0, inf) handles without cutting it off.
    val, _ = quad(lambda x: float(np.exp(-_rho_numpy(x, alpha))), 0.0, np.inf,
                  epsabs=1e-13, epsrel=1e-12, limit=500)
    return 2.0 * val


QUADRATURE_STEP = 1.0 / 16.0
"""Step of :func:`partition_table`'s trapezoidal rule in the transformed variable."""

QUADRATURE_SPAN = 4.5
"""The transformed variable runs over [-span, span]: x from about 1e-31 to 1e31."""


def partition_table(alphas: np.ndarray) -> np.ndarray:
    """``Z(alpha)`` of many shapes at once: :func:`partition_numeric`, vectorised.

    The half line is mapped by ``x = exp(pi / 2 sinh t)`` (a double-exponential rule: the
    integrand then decays doubly exponentially at both ends of t, for the algebraic tail of
    alpha = 0 as for the Gaussian of alpha = 2) and integrated by the trapezoidal rule in t.
    It agrees with ``quad`` at the spline's knots to near machine precision
    (docs/decisions/implementation-speed.md).

    Parameters
    ----------
    alphas : (n,) float
        Shapes in [0, 2].

    Returns
    -------
    (n,) float64
    """
    alphas = np.asarray(alphas, dtype=np.float64)
    if alphas.size and not (alphas.min() >= 0.0 and alphas.max() <= ALPHA_TABLE_MAX):
        raise RegnfError(f"the partition function is tabulated for alpha in [0, 2], got {alphas.min()}..{alphas.max()}")
    h = QUADRATURE_STEP
    t = np.arange(-QUADRATURE_SPAN, QUADRATURE_SPAN + 0.5 * h, h)
    x = np.exp(0.5 * np.pi * np.sinh(t))
    dx = h * 0.5 * np.pi * np.cosh(t) * x
    with np.errstate(over="ignore"):
        return 2.0 * (np.exp(-_rho_numpy(x[None, :], alphas[:, None])) * dx).sum(axis=1)


class _Spline(NamedTuple):
    """A cubic spline: ``f(a) = sum_k coef[k, i] (a - knots[i])^(3 - k)`` on [knots[i], knots[i+1]]."""

    knots: np.ndarray
    coef: np.ndarray


def _knots() -> np.ndarray:
    """Spline knots on [0, 2]: geometric towards both ends, uniform in the middle."""
    graded = [TABLE_END_GAP]
    while TABLE_GRADING * graded[-1] < TABLE_MAX_SPACING:
        graded.append(graded[-1] * (1.0 + TABLE_GRADING))
    g = np.asarray(graded)
    n = int(np.ceil((ALPHA_TABLE_MAX - 2.0 * g[-1]) / TABLE_MAX_SPACING))
    middle = np.linspace(g[-1], ALPHA_TABLE_MAX - g[-1], n + 1)
    return np.unique(np.concatenate([[0.0], g, middle, ALPHA_TABLE_MAX - g, [ALPHA_TABLE_MAX]]))


@lru_cache(maxsize=1)
def _log_partition_spline() -> _Spline:
    from scipy.interpolate import CubicSpline

    alphas = _knots()
    log_z = np.log(partition_table(alphas))
    spline = CubicSpline(alphas, log_z, bc_type="not-a-knot")
    return _Spline(alphas, np.asarray(spline.c))


@lru_cache(maxsize=8)
def _spline_tensors(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    sp = _log_partition_spline()
    return (torch.as_tensor(sp.knots, device=device, dtype=dtype),
            torch.as_tensor(sp.coef, device=device, dtype=dtype))


def log_partition(alpha: torch.Tensor) -> torch.Tensor:
    """``log Z(alpha)``, differentiable in alpha (cubic spline through a quadrature table).

    Parameters
    ----------
    alpha : (...) float tensor
        Shapes in [0, 2]; values outside are clamped to the table.

    Returns
    -------
    (...) float tensor, same dtype and device as ``alpha``.
    """
    # Evaluated in float64: knots 1e-9 from the ends do not survive float32 rounding.
    knots, coef = _spline_tensors(alpha.device, torch.float64)
    a = alpha.double().clamp(0.0, ALPHA_TABLE_MAX)
    i = torch.searchsorted(knots, a.detach().contiguous(), right=True) - 1
    i = i.clamp(0, knots.shape[0] - 2)
    u = a - knots[i]
    return (((coef[0, i] * u + coef[1, i]) * u + coef[2, i]) * u + coef[3, i]).to(alpha.dtype)


def general_rho(x: torch.Tensor, alpha: torch.Tensor | float, scale: torch.Tensor | float) -> torch.Tensor:
    """Barron's general robust loss ``rho(x, alpha, c)`` (elementwise, broadcasting).

    Parameters
    ----------
    x : (...) float tensor
        Residuals.
    alpha : (...) float tensor or float
        Shape, >= 0 (0: Cauchy-like log loss, 1: pseudo-Huber / Charbonnier, 2: L2).
    scale : (...) float tensor or float
        ``c > 0``: residuals well below ``c`` are penalised quadratically.

    Returns
    -------
    (...) float tensor
    """
    alpha = torch.as_tensor(alpha, dtype=x.dtype, device=x.device)
    scale = torch.as_tensor(scale, dtype=x.dtype, device=x.device)
    z2 = (x / scale) ** 2
    beta = (alpha - 2.0).abs().clamp(min=_SAFE_EPS)
    a_safe = alpha.clamp(min=_SAFE_EPS)
    # expm1/log1p keep the small-alpha and small-residual regimes accurate in float32.
    general = beta / a_safe * torch.expm1(0.5 * a_safe * torch.log1p(z2 / beta))
    out = torch.where(alpha == 0.0, torch.log1p(0.5 * z2), general)
    return torch.where(alpha == 2.0, 0.5 * z2, out)


def robust_nll(x: torch.Tensor, alpha: torch.Tensor | float, scale: torch.Tensor | float) -> torch.Tensor:
    """Negative log-likelihood ``rho(x, alpha, c) + log c + log Z(alpha)`` (elementwise).

    ``exp(-robust_nll)`` integrates to 1 over x for every alpha in [0, 2] and c > 0.

    Parameters
    ----------
    x : (...) float tensor
    alpha : (...) float tensor or float
        In [0, 2].
    scale : (...) float tensor or float
        > 0.

    Returns
    -------
    (...) float tensor
    """
    alpha = torch.as_tensor(alpha, dtype=x.dtype, device=x.device)
    scale = torch.as_tensor(scale, dtype=x.dtype, device=x.device)
    return general_rho(x, alpha, scale) + torch.log(scale) + log_partition(alpha)


def _inverse_softplus(y: float) -> float:
    # log(expm1(y)), written to stay finite for large y.
    return y + math.log(-math.expm1(-y))


class AdaptiveRobustLoss(torch.nn.Module):
    """Barron's adaptive loss with learnt shape ``alpha`` and scale ``c``, as an NLL.

    The latent parameters are unconstrained; ``alpha = alpha_lo + (alpha_hi - alpha_lo)
    sigmoid(latent_alpha)`` stays in (alpha_lo, alpha_hi) and ``c = scale_lo +
    softplus(latent_scale)`` stays above ``scale_lo``. ``groups`` independent (alpha, c) pairs
    are held (one per registration hypothesis when several are refined in one batch); each
    residual picks its pair by index.

    Parameters
    ----------
    groups : int
        Number of independent (alpha, c) pairs.
    alpha_lo, alpha_hi : float
        Allowed shape range, ``0 <= alpha_lo < alpha_hi <= 2``. Reg-NF: (0, 1]; the default
        floor 1e-6 is nerf2nerf's.
    alpha_init : float, optional
        Initial shape; default the middle of the range (Barron's default).
    scale_lo : float
        Smallest scale (Barron's default 1e-5).
    scale_init : float
        Initial scale (*paper*: 1).
    """

    def __init__(
        self,
        groups: int = 1,
        alpha_lo: float = 1e-6,
        alpha_hi: float = 1.0,
        alpha_init: float | None = None,
        scale_lo: float = 1e-5,
        scale_init: float = 1.0,
    ) -> None:
        super().__init__()
        if int(groups) < 1:
            raise RegnfError(f"groups must be >= 1, got {groups}")
        if not 0.0 <= alpha_lo < alpha_hi <= ALPHA_TABLE_MAX:
            raise RegnfError(f"need 0 <= alpha_lo < alpha_hi <= 2, got ({alpha_lo}, {alpha_hi})")
        if alpha_init is None:
            alpha_init = 0.5 * (alpha_lo + alpha_hi)
        if not alpha_lo < alpha_init < alpha_hi:
            raise RegnfError(f"alpha_init {alpha_init} must lie strictly inside ({alpha_lo}, {alpha_hi})")
        if not scale_lo > 0.0 or not scale_init > scale_lo:
            raise RegnfError(f"need 0 < scale_lo < scale_init, got {scale_lo}, {scale_init}")
        self.alpha_lo, self.alpha_hi, self.scale_lo = float(alpha_lo), float(alpha_hi), float(scale_lo)
        frac = (alpha_init - alpha_lo) / (alpha_hi - alpha_lo)
        self.latent_alpha = torch.nn.Parameter(
            torch.full((int(groups),), math.log(frac / (1.0 - frac)), dtype=torch.float32))
        self.latent_scale = torch.nn.Parameter(
            torch.full((int(groups),), _inverse_softplus(scale_init - scale_lo), dtype=torch.float32))

    @property
    def groups(self) -> int:
        return int(self.latent_alpha.shape[0])

    @property
    def alpha(self) -> torch.Tensor:
        """(groups,) shape parameters in (alpha_lo, alpha_hi)."""
        return self.alpha_lo + (self.alpha_hi - self.alpha_lo) * torch.sigmoid(self.latent_alpha)

    @property
    def scale(self) -> torch.Tensor:
        """(groups,) scale parameters ``c > scale_lo``."""
        return self.scale_lo + torch.nn.functional.softplus(self.latent_scale)

    def forward(self, residuals: torch.Tensor, group: torch.Tensor | None = None) -> torch.Tensor:
        """Per-element negative log-likelihood.

        Parameters
        ----------
        residuals : (n,) float
        group : (n,) long, optional
            Which (alpha, c) pair each residual uses; may be omitted when ``groups == 1``.

        Returns
        -------
        (n,) float
        """
        if residuals.ndim != 1:
            raise RegnfError(f"residuals must be a 1-D tensor, got shape {tuple(residuals.shape)}")
        alpha = self.alpha.to(residuals.dtype)
        scale = self.scale.to(residuals.dtype)
        if group is None:
            if self.groups != 1:
                raise RegnfError(f"{self.groups} (alpha, c) groups: pass `group` for every residual")
            return robust_nll(residuals, alpha[0], scale[0])
        if group.shape != residuals.shape:
            raise RegnfError(f"group {tuple(group.shape)} must match residuals {tuple(residuals.shape)}")
        return robust_nll(residuals, alpha[group], scale[group])

    @torch.no_grad()
    def assign(self, index: torch.Tensor, alpha: torch.Tensor, scale: torch.Tensor) -> None:
        """Set the pairs ``index`` (k,) long to the shapes ``alpha`` (k,) and scales ``scale`` (k,)
        (clamped just inside the allowed ranges)."""
        span = self.alpha_hi - self.alpha_lo
        frac = ((alpha.double() - self.alpha_lo) / span).clamp(1e-9, 1.0 - 1e-9)
        self.latent_alpha[index] = torch.log(frac / (1.0 - frac)).to(self.latent_alpha.dtype)
        y = (scale.double() - self.scale_lo).clamp(min=1e-12)
        latent = y + torch.log(-torch.expm1(-y))  # inverse softplus, finite for large y
        self.latent_scale[index] = latent.to(self.latent_scale.dtype)

