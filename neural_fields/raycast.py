"""Pinhole rays, a robust sphere tracer and a field renderer.

The tracer is built for approximate (neural) SDFs, which over- or under-estimate the true
distance: it takes under-relaxed steps, never steps less than a minimum, detects the sign
change of an overshoot and then bisects between the last positive and the first
non-positive sample. Rays start where they enter the field's bounds, so empty space around
the object costs nothing.

Cameras use the OpenCV convention (x right, y down, z forward) and are posed in the FIELD
frame (the renderer's world is the field frame; compose with ``inverse(field.to_world)`` for
a camera posed in metres). Depths are z-depths in field units.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np
import torch

from regnf.core.cameras import ray_aabb

from .field import DEFAULT_CHUNK, Field

Rays = TypeVar("Rays", bound=tuple)
"""A named tuple of per-ray tensors (first dimension: the ray)."""


@dataclass(frozen=True)
class SphereTraceConfig:
    """Settings of :func:`sphere_trace` (distances in field units)."""

    max_steps: int = 256
    """Marching steps per ray before it is given up as a miss."""
    step_factor: float = 0.9
    """Step = step_factor * sdf; below 1 so that SDFs that overestimate still rarely overshoot."""
    min_step: float = 1e-4
    """Smallest step, so that grazing rays do not stall; an overshoot it causes is bisected."""
    tol: float = 1e-5
    """A sample with 0 <= sdf < tol (marching) or |sdf| < tol (bisection) is the hit."""
    max_bisection: int = 20
    """Bisection iterations after an overshoot; then the bracket is interpolated linearly."""
    bounds_pad: float = 1e-3
    """The bounds are grown by this much for the entry/exit slab test."""
    chunk: int = DEFAULT_CHUNK
    """Rays traced (and shaded, in :func:`render_field`) per batch, to bound memory."""

    def __post_init__(self) -> None:
        if self.max_steps < 1 or self.max_bisection < 0 or self.chunk < 1:
            raise ValueError("max_steps and chunk must be >= 1 and max_bisection >= 0")
        if not 0 < self.step_factor <= 1.5:
            raise ValueError(f"step_factor must be in (0, 1.5], got {self.step_factor}")
        if self.min_step < 0 or self.tol <= 0 or self.bounds_pad < 0:
            raise ValueError("min_step and bounds_pad must be >= 0 and tol > 0")


class TraceResult(NamedTuple):
    """What :func:`sphere_trace` found for each of ``n`` rays."""

    hit: torch.Tensor
    """(n,) bool."""
    t: torch.Tensor
    """(n,) float: distance along the unit direction to the hit; +inf where missed."""
    points: torch.Tensor
    """(n, 3) float: hit points ``o + t d``; 0 where missed."""
    steps: torch.Tensor
    """(n,) int64: field (SDF) evaluations spent on each ray, bisection included."""


class RenderOutput(NamedTuple):
    """An image of a field (on the field's device)."""

    rgb: torch.Tensor
    """(H, W, 3) float in [0, 1], the background where missed."""
    depth: torch.Tensor
    """(H, W) float: z-depth in field units; 0 where missed."""
    mask: torch.Tensor
    """(H, W) bool: the pixel is covered (at least half of its sub-samples hit)."""
    normals: torch.Tensor
    """(H, W, 3) float: unit outward normals in the field frame; 0 where missed."""


# -- cameras ---------------------------------------------------------------------------------
def _check_camera(
    K: torch.Tensor | np.ndarray, camtoworld: torch.Tensor | np.ndarray, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    Kt = (
        torch.as_tensor(
            np.asarray(K) if not isinstance(K, torch.Tensor) else K, dtype=torch.float64
        )
        .detach()
        .cpu()
    )
    C = (
        torch.as_tensor(
            np.asarray(camtoworld) if not isinstance(camtoworld, torch.Tensor) else camtoworld,
            dtype=torch.float64,
        )
        .detach()
        .cpu()
    )
    if (
        Kt.shape != (3, 3)
        or not bool(torch.isfinite(Kt).all())
        or abs(float(torch.linalg.det(Kt))) < 1e-12
    ):
        raise ValueError(f"K must be a finite invertible 3x3 matrix, got {Kt.tolist()}")
    if C.shape != (4, 4) or not bool(torch.isfinite(C).all()):
        raise ValueError(f"camtoworld must be a finite 4x4 matrix, got shape {tuple(C.shape)}")
    if abs(float(torch.linalg.det(C[:3, :3]))) < 1e-12:
        raise ValueError("camtoworld has a singular rotation part")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"width and height must be positive integers, got {width} x {height}")
    return Kt, C


def _rays_through(
    Kt: torch.Tensor, C: torch.Tensor, u: torch.Tensor, v: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """float64 rays through image points ``(u, v)`` (n,) each, in continuous pixel coordinates."""
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # (n, 3)
    d_cam = pix @ torch.linalg.inv(Kt).T
    R = C[:3, :3]
    dirs = torch.nn.functional.normalize(d_cam @ R.T, dim=-1)
    forward = torch.nn.functional.normalize(R[:, 2], dim=0)
    z_scale = dirs @ forward
    origins = C[:3, 3].expand_as(dirs)
    return origins, dirs, z_scale


def pinhole_rays(
    K: torch.Tensor | np.ndarray,
    camtoworld: torch.Tensor | np.ndarray,
    width: int,
    height: int,
    stride: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays through the centres of (every ``stride``-th) pixel of a pinhole camera.

    Pixel ``(u, v)`` (column, row) is sampled at ``(u + 0.5, v + 0.5)``; rays are ordered
    row-major (``v`` outer, ``u`` inner), ``u = 0, stride, 2 stride, ...``.

    Parameters
    ----------
    K : (3, 3) float
        Intrinsics.
    camtoworld : (4, 4) float
        Camera -> field-frame pose, OpenCV axes (x right, y down, z forward).
    width, height : int
        Image size in pixels.
    stride : int
        Keep every ``stride``-th pixel along both axes.
    device : torch.device or str, optional
        CPU by default.
    dtype : torch.dtype
        Of the outputs; rays are computed in float64 first.

    Returns
    -------
    origins : (n, 3) float
    dirs : (n, 3) float
        Unit directions.
    z_scale : (n,) float
        ``dot(dir, camera forward)``, so that z-depth = ``t * z_scale``.
    """
    Kt, C = _check_camera(K, camtoworld, width, height)
    if int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride}")
    us = torch.arange(0, int(width), int(stride), dtype=torch.float64) + 0.5
    vs = torch.arange(0, int(height), int(stride), dtype=torch.float64) + 0.5
    v, u = torch.meshgrid(vs, us, indexing="ij")
    o, d, z = _rays_through(Kt, C, u.reshape(-1), v.reshape(-1))
    return tuple(a.to(device=device, dtype=dtype) for a in (o, d, z))  # type: ignore[return-value]


# -- tracing ---------------------------------------------------------------------------------
def check_rays(origins: torch.Tensor, dirs: torch.Tensor, near: float, far: float,
               unit: bool = False) -> None:
    """Raise ``ValueError`` unless ``origins``, ``dirs`` are both (n, 3), ``0 <= near < far``
    and (with ``unit``) every direction has unit length."""
    if origins.ndim != 2 or origins.shape[-1] != 3 or origins.shape != dirs.shape:
        raise ValueError(
            "origins and dirs must both be (n, 3), got "
            f"{tuple(origins.shape)} and {tuple(dirs.shape)}"
        )
    if not (near >= 0 and far > near):
        raise ValueError(f"need 0 <= near < far, got near={near}, far={far}")
    if unit and dirs.shape[0] > 0:
        norm_err = float((torch.linalg.vector_norm(dirs, dim=-1) - 1.0).abs().max())
        if not norm_err < 1e-4:
            raise ValueError(f"dirs must be unit vectors (largest |norm - 1| = {norm_err:.3g})")


def by_chunks(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    chunk: int,
    device: torch.device | str,
    per_chunk: Callable[[torch.Tensor, torch.Tensor], Rays],
    empty: Callable[[], Rays],
) -> Rays:
    """``per_chunk`` on ``chunk`` rays at a time (moved to ``device``), results concatenated.

    Parameters
    ----------
    origins, dirs : (n, 3) float
        The rays.
    chunk : int
        Rays per call (bounds the memory of one call).
    device : torch.device or str
        Where each chunk is computed (the field's device).
    per_chunk : callable
        ``(origins, dirs) -> named tuple`` of tensors whose first dimension is the chunk's rays.
    empty : callable
        The result for no ray at all.
    """
    parts = [per_chunk(origins[i : i + chunk].to(device), dirs[i : i + chunk].to(device))
             for i in range(0, origins.shape[0], chunk)]
    if not parts:
        return empty()
    return type(parts[0])(*(torch.cat(list(per_ray)) for per_ray in zip(*parts, strict=True)))


@torch.no_grad()
def sphere_trace(
    field: Field,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    near: float = 0.0,
    far: float = math.inf,
    config: SphereTraceConfig = SphereTraceConfig(),
) -> TraceResult:
    """Intersect rays with the zero level set of ``field``.

    Each ray marches from where it enters the field's bounds (or ``near``) with steps
    ``max(step_factor * sdf, min_step)``. A sample with ``0 <= sdf < tol`` is a hit; a
    sample with ``sdf < 0`` after a positive one brackets the surface, which is then bisected
    to ``|sdf| < tol``. A ray whose FIRST sample is already negative starts inside matter
    (for example cut by ``near`` or the bounds) and is a hit at its start. Rays that leave
    ``[near, far]`` or the bounds, return a non-finite SDF, or run out of steps are misses.

    Parameters
    ----------
    field : Field
    origins : (n, 3) float
        In the field frame.
    dirs : (n, 3) float
        Unit directions.
    near, far : float
        Range of ``t`` searched.
    config : SphereTraceConfig

    Returns
    -------
    TraceResult
        On the device of ``origins``; computed on the field's device.
    """
    check_rays(origins, dirs, near, far)

    def empty() -> TraceResult:
        z = origins.new_zeros(0)
        return TraceResult(z.bool(), z, origins.new_zeros(0, 3), z.long())

    hits = by_chunks(origins, dirs, config.chunk, field.device,
                     lambda o, d: _trace_chunk(field, o, d, near, far, config), empty)
    return TraceResult(*(x.to(origins.device) for x in hits))


def _trace_chunk(
    field: Field, o: torch.Tensor, d: torch.Tensor, near: float, far: float, cfg: SphereTraceConfig
) -> TraceResult:
    n = o.shape[0]
    lo = field.bounds[0].to(o.dtype) - cfg.bounds_pad
    hi = field.bounds[1].to(o.dtype) + cfg.bounds_pad
    t_in, t_out = ray_aabb(o, d, lo, hi)
    t_start = t_in.clamp(min=near)
    t_end = t_out.clamp(max=far)

    t = t_start.clone()
    steps = torch.zeros(n, dtype=torch.long, device=o.device)
    hit = torch.zeros(n, dtype=torch.bool, device=o.device)
    seen_positive = torch.zeros_like(hit)
    t_pos = t_start.clone()  # last t with sdf > 0: the outside end of a bracket
    s_pos = torch.zeros_like(t)
    s_neg = torch.zeros_like(t)
    bracketed = torch.zeros_like(hit)
    # Indices of the rays still marching: compacted every step, so a step costs O(active).
    idx = (t_start <= t_end).nonzero().squeeze(1)

    # March. A loop over STEPS; each step evaluates only the still-active rays.
    for _ in range(cfg.max_steps):
        if idx.numel() == 0:
            break
        ti = t[idx]
        s = field.sdf(o[idx] + ti[:, None] * d[idx])
        steps[idx] += 1
        finite = torch.isfinite(s)
        close = finite & (s >= 0) & (s < cfg.tol)
        negative = finite & (s < 0)
        start_inside = negative & ~seen_positive[idx]
        crossed = negative & seen_positive[idx]
        hit[idx[close | start_inside]] = True
        bracketed[idx[crossed]] = True
        s_neg[idx[crossed]] = s[crossed]

        moving = finite & (s >= cfg.tol)
        mi, tm, sm = idx[moving], ti[moving], s[moving]
        t_pos[mi], s_pos[mi], seen_positive[mi] = tm, sm, True
        t_next = tm + (cfg.step_factor * sm).clamp(min=cfg.min_step)
        t[mi] = t_next
        idx = mi[t_next <= t_end[mi]]  # past the exit of the bounds (or far): a miss

    # Bisect every bracketed ray together: [t_pos (sdf > 0), t (sdf < 0)].
    a, b = t_pos.clone(), t.clone()
    idx = bracketed.nonzero().squeeze(1)
    for _ in range(cfg.max_bisection):
        if idx.numel() == 0:
            break
        mid = 0.5 * (a[idx] + b[idx])
        s = field.sdf(o[idx] + mid[:, None] * d[idx])
        steps[idx] += 1
        done = s.abs() < cfg.tol
        outside = ~done & (s > 0)
        inside = ~done & ~outside  # includes a NaN sample: shrink towards the known outside
        t[idx[done]] = mid[done]
        a[idx[outside]], s_pos[idx[outside]] = mid[outside], s[outside]
        b[idx[inside]], s_neg[idx[inside]] = mid[inside], s[inside]
        idx = idx[~done]
    # Unconverged brackets: one false-position estimate, no further evaluation.
    if idx.numel() > 0:
        denom = (s_pos[idx] - s_neg[idx]).clamp(min=torch.finfo(t.dtype).tiny)
        frac = (s_pos[idx] / denom).nan_to_num(0.5).clamp(0.0, 1.0)
        t[idx] = a[idx] + frac * (b[idx] - a[idx])
    hit |= bracketed

    t = torch.where(hit, t, torch.full_like(t, math.inf))
    points = torch.where(
        hit[:, None], o + t.nan_to_num(0.0, posinf=0.0)[:, None] * d, torch.zeros_like(o)
    )
    return TraceResult(hit, t, points, steps)


# -- rendering -------------------------------------------------------------------------------
@torch.no_grad()
def render_field(
    field: Field,
    K: torch.Tensor | np.ndarray,
    camtoworld: torch.Tensor | np.ndarray,
    width: int,
    height: int,
    background: Sequence[float] = (0.5, 0.5, 0.5),
    supersample: int = 1,
    near: float = 0.0,
    far: float = math.inf,
    config: SphereTraceConfig = SphereTraceConfig(),
) -> RenderOutput:
    """Sphere-trace an image of ``field``.

    With ``supersample = s``, each pixel is sampled by ``s x s`` rays through the centres of
    a regular sub-grid and the colour is box-filtered over them (missed samples count as
    the background), which matches MSAA-resolved ground truth. The other outputs use the
    average over the sub-samples that HIT: ``mask`` is coverage >= 1/2, ``depth`` the mean
    z-depth of the hits and ``normals`` their normalised mean (both 0 outside the mask).

    Parameters
    ----------
    field : Field
    K : (3, 3) float
        Intrinsics.
    camtoworld : (4, 4) float
        Camera -> field-frame pose, OpenCV axes.
    width, height : int
    background : (3,) float
        RGB of missed samples.
    supersample : int
        Sub-samples per pixel along each axis, >= 1.
    near, far : float
        Range of ``t`` searched along each (unit) ray.
    config : SphereTraceConfig
        ``config.chunk`` rays are traced and shaded at a time.

    Returns
    -------
    RenderOutput
        On the field's device.
    """
    Kt, C = _check_camera(K, camtoworld, width, height)
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample}")
    bg = torch.as_tensor(background, dtype=torch.float32)
    if bg.shape != (3,):
        raise ValueError(f"background must be RGB, got {bg.tolist()}")
    W, H, S = int(width), int(height), int(supersample)
    dev = field.device

    dtype = field.bounds.dtype  # rays in the field's working precision
    n = H * W * S * S
    rgb = bg.to(device=dev, dtype=dtype).expand(n, 3).clone()
    normals = torch.zeros(n, 3, device=dev, dtype=dtype)
    depth = torch.zeros(n, device=dev, dtype=dtype)
    hit = torch.zeros(n, dtype=torch.bool, device=dev)
    # A loop over chunks of samples: rays are generated, traced and shaded a chunk at a time,
    # so memory beyond the output images is bounded by ``config.chunk``.
    for start in range(0, n, config.chunk):
        flat = torch.arange(start, min(start + config.chunk, n), dtype=torch.long)
        # Samples ordered (v, u, sub_v, sub_u), so that a reshape groups each pixel's.
        su, sv = flat % S, (flat // S) % S
        u, v = (flat // (S * S)) % W, flat // (S * S * W)
        uf = u.double() + (su.double() + 0.5) / S
        vf = v.double() + (sv.double() + 0.5) / S
        o, d, z = (a.to(device=dev, dtype=dtype) for a in _rays_through(Kt, C, uf, vf))
        tr = sphere_trace(field, o, d, near=near, far=far, config=config)
        rows = flat.to(dev)[tr.hit]
        hit[rows] = True
        if rows.numel() > 0:
            p, dh = tr.points[tr.hit], d[tr.hit]
            rgb[rows] = field.color(p, dh).to(dtype).clamp(0.0, 1.0)
            normals[rows] = field.normal(p).to(dtype)
            depth[rows] = tr.t[tr.hit] * z[tr.hit]

    # Resolve the sub-samples of each pixel.
    n_hit = hit.reshape(H, W, S * S).sum(-1).to(dtype)
    mask = n_hit >= 0.5 * S * S
    rgb_img = rgb.reshape(H, W, S * S, 3).mean(dim=2)
    depth_img = depth.reshape(H, W, S * S).sum(-1) / n_hit.clamp(min=1.0)
    nrm_img = torch.nn.functional.normalize(normals.reshape(H, W, S * S, 3).sum(dim=2), dim=-1)
    depth_img = torch.where(mask, depth_img, torch.zeros_like(depth_img))
    nrm_img = torch.where(mask[..., None], nrm_img, torch.zeros_like(nrm_img))
    return RenderOutput(rgb_img, depth_img, mask, nrm_img)
