"""NeuS-style volume rendering of a neural SDF along rays (the optional colour loss).

Opacity between two samples comes from the SDF through a logistic CDF with sharpness
``inv_s`` (NeuS, Wang et al. 2021): ``alpha_i = max((Phi(s f_i) - Phi(s f_{i+1})) / Phi(s f_i), 0)``,
transmittance ``T_i = prod_{j<i} (1 - alpha_j)``, colour ``sum_i T_i alpha_i c_i``. Colour
gradients reach the geometry through the weights, which is what makes this loss useful
where depth is missing or unreliable.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from regnf.fields.neural_sdf import NeuralSDF

TRAINING_EPS = 1e-7
"""Added to every ``1 - alpha`` of the transmittance in training: an opaque interval
(``alpha = 1``) would otherwise zero the product, and with it every gradient that flows
through the samples behind it."""


def neus_weights(sdf: torch.Tensor, inv_s: float, eps: float = 0.0) -> torch.Tensor:
    """NeuS interval weights (r, m - 1) from SDF samples ``sdf`` (r, m) ordered along each ray.

    ``alpha_i = clamp((Phi(s f_i) - Phi(s f_{i+1})) / Phi(s f_i), 0, 1)`` with ``Phi`` the logistic
    CDF of sharpness ``s = inv_s``, transmittance ``T_i = prod_{j<i} (1 - alpha_j + eps)``,
    weight ``T_i alpha_i``. ``eps``: 0 to render, :data:`TRAINING_EPS` to train.
    """
    cdf = torch.sigmoid(sdf * inv_s)
    alpha = ((cdf[:, :-1] - cdf[:, 1:]) / cdf[:, :-1].clamp_min(1e-6)).clamp(0.0, 1.0)
    ones = torch.ones_like(alpha[:, :1])
    keep = 1.0 - alpha + eps if eps else 1.0 - alpha
    return torch.cumprod(torch.cat([ones, keep], dim=1), dim=1)[:, :-1] * alpha


def render_rays_neus(
    field: NeuralSDF,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    near: torch.Tensor,
    far: torch.Tensor,
    n_samples: int,
    inv_s: float,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Volume-rendered colour (r, 3) and opacity (r,) of ``r`` rays between ``near`` and ``far`` (r,).

    Samples are stratified (one jittered sample per interval). Normals fed to the colour head
    are the SDF gradient by autograd, detached: grid_sample has no second derivative.
    """
    r = origins.shape[0]
    u = torch.rand(r, n_samples, generator=generator).to(origins.device)
    edges = torch.linspace(0.0, 1.0, n_samples + 1, device=origins.device)[:-1]
    frac = edges[None] + u / n_samples
    t = near[:, None] + (far - near)[:, None] * frac  # (r, n)
    pts = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)
    with torch.enable_grad():
        xg = pts.detach().requires_grad_(True)
        (g,) = torch.autograd.grad(field.sdf(xg).sum(), xg)
    sdf, feat = field.sdf_and_features(pts)
    normals = F.normalize(g, dim=-1).detach()
    rgb = field.color_from(feat, normals, dirs.repeat_interleave(n_samples, 0)).view(r, n_samples, 3)
    weights = neus_weights(sdf.view(r, n_samples), inv_s, TRAINING_EPS)  # (r, n - 1)
    mid = 0.5 * (rgb[:, :-1] + rgb[:, 1:])
    return (weights[..., None] * mid).sum(dim=1), weights.sum(dim=1)
