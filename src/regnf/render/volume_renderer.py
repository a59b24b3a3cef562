"""NeuS-style volume rendering of any field, for comparison with the sphere tracer.

Each ray, clipped to the field's bounds, gets ``n_samples`` samples evenly spaced over its
segment (the authors use 200 uniform samples), optionally ``n_importance`` more drawn from
the coarse weights (inverse CDF at stratified, deterministic quantiles). Opacity of the
interval between consecutive samples comes from the SDF through the logistic CDF
``Phi(x) = sigmoid(inv_s x)`` (Wang et al. 2021)::

    alpha_i = clamp((Phi(f_i) - Phi(f_{i+1})) / Phi(f_i), 0, 1)
    w_i     = alpha_i prod_{j<i} (1 - alpha_j)

Colour and normal of an interval are taken at its midpoint; the outputs are the
``w``-weighted sums. Depth is the EXPECTED depth normalised by the accumulated opacity,
``sum w_i t_i / sum w_i`` (so a half-covered pixel is not pulled towards the camera), and
the mask is opacity > ``mask_threshold``. Intervals of weight below ``shade_min_weight``
are not shaded (their colour cannot show in 8 bits). ``evals_per_pixel`` counts the SDF
samples (composite costs included), not the shading queries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from regnf.core.cameras import ray_aabb
from regnf.core.errors import RegnfError
from regnf.core.render_result import Render
from regnf.fields.field import Field
from regnf.fields.shading import check_camera_outside, world_rotation
from regnf.render.camera import Camera, camera_rays
from regnf.render.sphere_tracer import BACKGROUND_ID, by_chunks, check_rays
from regnf.training.volume_render import neus_weights


@dataclass(frozen=True)
class VolumeRendererConfig:
    """Settings of :func:`render_volume` (distances in FIELD units unless noted)."""

    n_samples: int = 200
    """Uniform samples per ray (endpoints of the ray's segment included), >= 2."""
    n_importance: int = 0
    """Extra samples per ray drawn from the coarse weights (NeuS's hierarchical sampling)."""
    inv_s: float = 512.0
    """Sharpness ``s`` of the logistic density, 1 / field units: larger is a thinner shell."""
    jitter: bool = False
    """Stratified random offsets of the uniform samples (False: deterministic)."""
    seed: int = 0
    """Seed of the jitter."""
    mask_threshold: float = 0.5
    """A pixel is covered where the accumulated opacity exceeds this."""
    shade_min_weight: float = 1e-5
    """Intervals lighter than this are not shaded."""
    near: float = 0.0
    """METRES from the camera before which nothing is integrated."""
    far: float = math.inf
    """METRES from the camera beyond which nothing is integrated."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """RGB behind the volume."""
    bounds_pad: float = 1e-3
    """The bounds are grown by this much for the ray clipping."""
    chunk: int = 1024
    """Rays per batch (each costs ``n_samples + n_importance`` points)."""
    check_camera: bool = True
    """Refuse a camera whose centre is inside matter."""

    def __post_init__(self) -> None:
        if self.n_samples < 2 or self.n_importance < 0 or self.chunk < 1:
            raise RegnfError("need n_samples >= 2, n_importance >= 0 and chunk >= 1")
        if not (self.inv_s > 0 and math.isfinite(self.inv_s)):
            raise RegnfError(f"inv_s must be finite and > 0, got {self.inv_s}")
        if not 0.0 < self.mask_threshold < 1.0 or self.shade_min_weight < 0:
            raise RegnfError("need 0 < mask_threshold < 1 and shade_min_weight >= 0")
        if not (0 <= self.near < self.far) or self.bounds_pad < 0:
            raise RegnfError(
                f"need 0 <= near < far and bounds_pad >= 0, got {self.near}, {self.far}"
            )
        if len(self.background) != 3:
            raise RegnfError(f"background must be RGB, got {self.background!r}")


class VolumeHits(NamedTuple):
    """Per-ray results of :func:`integrate` (field frame)."""

    rgb: torch.Tensor
    """(n, 3) float: composited over the background."""
    t: torch.Tensor
    """(n,) float: expected distance along the ray (field units); 0 where opacity is 0."""
    normals: torch.Tensor
    """(n, 3) float: normalised weighted normal, FIELD frame; 0 where opacity is 0."""
    opacity: torch.Tensor
    """(n,) float in [0, 1]: accumulated weight."""
    winner: torch.Tensor
    """(n,) int64: component at the heaviest interval (0 scene); -1 where opacity is 0."""
    evals: torch.Tensor
    """(n,) int64: SDF evaluations spent on the ray."""


def _sdf_checked(field: Field, p: torch.Tensor):
    s = field.evaluate(p)
    bad = ~torch.isfinite(s.sdf)
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise RegnfError(
            f"field {field.name or type(field).__name__!r} returned a non-finite SDF "
            f"({float(s.sdf[k])}) at {int(bad.sum())} of {p.shape[0]} volume samples, for "
            f"example at field-frame point {p[k].tolist()}"
        )
    return s


def _importance(t: torch.Tensor, w: torch.Tensor, k: int) -> torch.Tensor:
    """``k`` samples (r, k) per ray from the piecewise-constant pdf ``w`` (r, m - 1) on ``t`` (r, m)."""
    pdf = w + 1e-5  # a floor keeps rays without any weight uniformly sampled
    pdf = pdf / pdf.sum(dim=1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), pdf.cumsum(dim=1)], dim=1)  # (r, m)
    u = ((torch.arange(k, device=t.device, dtype=t.dtype) + 0.5) / k).expand(t.shape[0], k)
    j = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp(1, t.shape[1] - 1)
    c0, c1 = cdf.gather(1, j - 1), cdf.gather(1, j)
    t0, t1 = t.gather(1, j - 1), t.gather(1, j)
    frac = ((u - c0) / (c1 - c0).clamp(min=1e-12)).clamp(0.0, 1.0)
    return t0 + frac * (t1 - t0)


@torch.no_grad()
def integrate(
    field: Field,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    config: VolumeRendererConfig = VolumeRendererConfig(),
) -> VolumeHits:
    """Volume-render rays ``origins``, ``dirs`` (n, 3) (field frame, unit directions).

    ``config.near`` and ``config.far`` are METRES, brought to field units by
    ``field.world_scale`` here. Computed ``config.chunk`` rays at a time.
    """
    near, far = config.near / field.world_scale, config.far / field.world_scale
    check_rays(origins, dirs, near, far)
    gen = torch.Generator(device="cpu").manual_seed(config.seed) if config.jitter else None
    dev = field.device

    def empty() -> VolumeHits:
        z = torch.zeros(0, device=dev)
        return VolumeHits(z.new_zeros(0, 3), z, z.new_zeros(0, 3), z, z.long(), z.long())

    return by_chunks(origins, dirs, config.chunk, dev,
                     lambda o, d: _integrate_chunk(field, o, d, near, far, config, gen), empty)


def _integrate_chunk(
    field: Field,
    o: torch.Tensor,
    d: torch.Tensor,
    near: float,
    far: float,
    cfg: VolumeRendererConfig,
    gen: torch.Generator | None,
) -> VolumeHits:
    n, dev, dtype = o.shape[0], o.device, o.dtype
    bg = torch.tensor(list(cfg.background), dtype=dtype, device=dev)
    out = VolumeHits(
        bg.expand(n, 3).clone(),
        torch.zeros(n, dtype=dtype, device=dev),
        torch.zeros(n, 3, dtype=dtype, device=dev),
        torch.zeros(n, dtype=dtype, device=dev),
        torch.full((n,), BACKGROUND_ID, dtype=torch.long, device=dev),
        torch.zeros(n, dtype=torch.long, device=dev),
    )
    lo = field.bounds[0].to(dtype) - cfg.bounds_pad
    hi = field.bounds[1].to(dtype) + cfg.bounds_pad
    t_in, t_out = ray_aabb(o, d, lo, hi)
    t0, t1 = t_in.clamp(min=near), t_out.clamp(max=far)
    rows = (t0 < t1).nonzero().squeeze(1)  # rays that cross the bounds at all
    if rows.numel() == 0:
        return out
    o, d, t0, t1 = o[rows], d[rows], t0[rows], t1[rows]
    r, m = rows.numel(), cfg.n_samples

    frac = torch.linspace(0.0, 1.0, m, device=dev, dtype=dtype).expand(r, m)
    if gen is not None:  # stratified jitter inside each interval, endpoints kept
        u = torch.rand(r, m, generator=gen, dtype=dtype).to(dev) - 0.5
        frac = (frac + u / (m - 1)).clamp(0.0, 1.0).sort(dim=1).values
    t = t0[:, None] + (t1 - t0)[:, None] * frac  # (r, m)

    def query(tt: torch.Tensor):
        pts = (o[:, None, :] + tt[..., None] * d[:, None, :]).reshape(-1, 3)
        s = _sdf_checked(field, pts)
        k = tt.shape[1]
        return s.sdf.to(dtype).view(r, k), s.winner.view(r, k), s.evals.view(r, k).sum(dim=1)

    sdf, win, evals = query(t)
    if cfg.n_importance > 0:
        t_new = _importance(t, neus_weights(sdf, cfg.inv_s), cfg.n_importance)
        sdf_new, win_new, evals_new = query(t_new)
        t, order = torch.cat([t, t_new], dim=1).sort(dim=1)
        sdf = torch.cat([sdf, sdf_new], dim=1).gather(1, order)
        win = torch.cat([win, win_new], dim=1).gather(1, order)
        evals = evals + evals_new
    w = neus_weights(sdf, cfg.inv_s)  # (r, k - 1)

    acc = w.sum(dim=1)
    t_mid = 0.5 * (t[:, :-1] + t[:, 1:])
    depth = (w * t_mid).sum(dim=1) / acc.clamp(min=1e-12)
    heavy = w.argmax(dim=1)
    winner = win.gather(1, (heavy + 1)[:, None])[:, 0]  # the interval's far (inside) end

    # Shade only the intervals that can show; vectorised over all of them at once.
    ri, ii = (w > cfg.shade_min_weight).nonzero(as_tuple=True)
    rgb_acc = torch.zeros(r, 3, dtype=dtype, device=dev)
    nrm_acc = torch.zeros(r, 3, dtype=dtype, device=dev)
    if ri.numel() > 0:
        p = o[ri] + t_mid[ri, ii][:, None] * d[ri]
        wi = w[ri, ii][:, None]
        _, g = field.sdf_and_gradient(p)  # enables autograd inside, returns detached
        col = field.color(p, d[ri]).to(dtype).clamp(0.0, 1.0)
        rgb_acc.index_add_(0, ri, wi * col)
        nrm_acc.index_add_(0, ri, wi * torch.nn.functional.normalize(g.to(dtype), dim=-1))

    some = acc > 0
    out.rgb[rows] = rgb_acc + (1.0 - acc)[:, None] * bg
    out.t[rows] = torch.where(some, depth, 0.0)
    out.normals[rows] = torch.nn.functional.normalize(nrm_acc, dim=-1)
    out.opacity[rows] = acc
    out.winner[rows] = torch.where(some, winner, BACKGROUND_ID)
    out.evals[rows] = evals
    return out


@torch.no_grad()
def render_volume(
    field: Field, camera: Camera, config: VolumeRendererConfig = VolumeRendererConfig()
) -> Render:
    """Volume-render one view of ``field`` from ``camera`` (posed in the field's metres).

    Same outputs and conventions as :func:`regnf.render.sphere_render.render`: depth is the
    opacity-normalised expected z-depth in metres (0 off the mask), normals in the world
    frame, instance id of the heaviest interval (-1 off the mask), no grid look-ups.
    Raises ``ValueError`` for a camera inside matter or non-finite field values; an empty
    view is all background.
    """
    rays = camera_rays(field, camera)
    if config.check_camera:
        check_camera_outside(field, rays.origin)
    ws = field.world_scale
    vh = integrate(field, rays.origins, rays.dirs, config)
    h, w = camera.height, camera.width
    mask = vh.opacity > config.mask_threshold
    depth = torch.where(mask, vh.t * rays.z_scale * ws, 0.0)
    normals = vh.normals @ world_rotation(field, vh.normals.dtype).T
    normals = torch.where(mask[:, None], normals, 0.0)
    ids = torch.where(mask, vh.winner, BACKGROUND_ID)
    return Render(
        rgb=vh.rgb.reshape(h, w, 3),
        depth=depth.reshape(h, w),
        normals=normals.reshape(h, w, 3),
        instance_id=ids.reshape(h, w),
        mask=mask.reshape(h, w),
        evals_per_pixel=vh.evals.reshape(h, w),
        lookups_per_pixel=torch.zeros_like(vh.evals).reshape(h, w),
    )
