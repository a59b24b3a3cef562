"""The one sphere tracer: of any field, with a composite's extra outputs.

Per ray (vectorised over rays; the loops are over STEPS, each touching only the rays still
active):

1. Rays are clipped to the field's bounds (and ``[near, far]``).
2. Empty-space skipping: where the coarse :class:`~regnf.neural_fields.distance_grid.DistanceGrid`
   guarantees at least ``grid_skip_cells`` cells of free space, the ray steps that far for
   one table look-up and no field evaluation. Not from the landing point of an unverified
   relaxed step, though, unless the grid's free sphere there overlaps the last safe sphere
   (the test of step 3 with the bound as ``|r|``): a relaxed step may have jumped over a thin
   surface, and free space around its landing point says nothing about the segment behind.
3. Otherwise the field is evaluated and the ray takes an over-relaxed step ``w * sdf``
   (Keinert et al. 2014, "Enhanced sphere tracing"). A relaxed step is safe only if the
   unbounding spheres before and after it overlap, ``r_prev + |r| >= step``; if they do
   not, the ray goes back to the plain step ``r_prev`` from the last safe point. Keinert
   then continues with ``w = 1`` (``adaptive=False``). By default the factor adapts
   instead: with ``m`` the rate at which the SDF fell between the last two samples (the
   incidence cosine, for a plane), the largest step whose spheres still overlap is
   ``2 r / (1 + m)``, so ``w = min(0.95 * 2 / (1 + m), cap)``, where the cap starts at
   ``omega`` and is halved towards 1 after each failure. This keeps the gain on flat
   surfaces seen at moderate incidence, where a fixed ``omega = 1.6`` fails at once (it
   exceeds the verifiable step for any incidence cosine above 0.25).
   An option, off by default, ``bracket_on_sign_change``: a relaxed step that lands
   INSIDE matter (``r < 0``) is bracketed and refined directly, overlap or not. That
   saves the slow approach of oblique rays to convex surfaces (about 20 % fewer
   evaluations on a sphere), but a thin surface in the unverified gap, in front of a
   thicker one, can then be skipped in favour of the one behind it.
4. A sample with ``|sdf| < tol(t)`` is a hit, with ``tol(t) = max(tol,
   footprint_fraction * t * pixel_angle)``: never finer than a fraction of the pixel
   footprint. Its ``t`` then gets one free secant correction ``r / m`` (``m`` the slope
   above), which removes most of the ``tol / cos(incidence)`` depth error. A sign change (a relaxed or minimum step crossed the surface) is bracketed
   and refined by Illinois false position (or plain bisection) to ``|sdf| < tol(t)``.

Before that, :func:`render_many` marches the rays of
each square tile of pixels (``cone_tile``) as one cone, one evaluation a step for the tile
(:func:`cone_starts`): the tile's rays then start where its cone came near a surface, at a
point proven free, instead of at the camera. The free space before the first surface is
crossed once a tile, not once a ray (8 baked views of a generated variant: 29.2 -> 14.4
evaluations a pixel, the cones' own included; 4.1 -> 2.4 s). A ray's result is still its own
trace's, from a later start: the same surfaces to the tracer's tolerance, not the same bits.

A ray whose first sample is inside matter (the bounds or ``near`` cut through an object)
is a hit at its start; a ray that leaves the bounds (or ``far``) or runs out of
``max_steps`` is a miss. Non-finite SDF values are an error, not a miss.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import torch

from regnf.core.cameras import ray_aabb
from regnf.core.render_result import Render
from regnf.neural_fields.camera import Camera, CameraRays, camera_rays
from regnf.neural_fields.distance_grid import DistanceGrid
from regnf.neural_fields.field import DEFAULT_CHUNK, Field, FieldSample
from regnf.neural_fields.shading import check_camera_outside, shade_hits

Rays = TypeVar("Rays", bound=tuple)
"""A named tuple of per-ray tensors (first dimension: the ray)."""
BACKGROUND_ID = -1
"""Instance id (winner) of a ray or pixel that hit nothing."""

WAVEFRONT = DEFAULT_CHUNK
"""Rays marching at once by default (65536). Smaller batches pay the loop's fixed cost more
often, larger ones miss the caches, and a view split over two batches takes more steps. Measured
on 2 cores: one view of 256 x 192 on two threads (``regnf bench render``) 4-10 % faster with
65536 than with 32768; the demo's 6 substitution views in two batches of 3 on two threads,
6.41-6.46 s with 65536 and 6.49 s with 32768; 8 views of a baked variant traced together on one
thread, 4.45, 4.05, 3.94 and 4.15 s with 8192, 16384, 32768 and 65536 (4.25 s a view at a time)."""
REFINE_METHODS = ("illinois", "bisection")
"""Root refinements of a bracketed crossing."""
ADAPTIVE_MARGIN = 0.95
"""Fraction of the largest verifiable relaxation that adaptive steps take."""
MIN_NEWTON_SLOPE = 0.1
"""Smallest SDF slope along the ray for the final secant correction of a hit."""


@dataclass(frozen=True)
class SphereTracerConfig:
    """Settings of :func:`trace` and :func:`render` (distances in FIELD units unless noted)."""

    max_steps: int = 256
    """Marching iterations per ray (look-ups and evaluations) before it counts as a miss."""
    omega: float = 1.6
    """Relaxation factor of the steps (the cap when adaptive), in (0, 2): above 1 over-relaxed
    (verified steps, see the module), 1 plain, below 1 under-relaxed for fields that overestimate
    their distance (registration's surface sampling takes 0.9 on neural fields)."""
    adaptive: bool = True
    """Adapt the relaxation to the SDF's slope along the ray (see the module); False: Keinert's
    fixed ``omega``, dropped to 1 for good after the first failed step."""
    min_step: float = 1e-4
    """Smallest step, so that grazing rays do not stall; an overshoot it causes is refined."""
    tol: float = 1e-5
    """Absolute hit tolerance on the SDF."""
    footprint_fraction: float = 1e-4
    """Hit tolerance as a fraction of the pixel footprint at the sample (0: absolute only)."""
    refine: str = "illinois"
    """Root refinement of a bracketed crossing: ``illinois`` (false position) or ``bisection``."""
    max_refine: int = 32
    """Refinement iterations; then the bracket is interpolated linearly."""
    bracket_on_sign_change: bool = False
    """Unsafe speed-up: a relaxed step that lands inside matter brackets the surface even if
    the unbounding spheres do not overlap (see the module). False: Keinert's fallback."""
    grid_resolution: int = 32
    """Cells per axis of the empty-space-skipping grid; 0 disables skipping."""
    grid_lipschitz: float = 1.0
    """Lipschitz constant assumed by the grid's bounds (> 1 for fields that overestimate)."""
    grid_skip_cells: float = 0.5
    """Skip by look-up only when the guaranteed free distance is this many (smallest) cells."""
    bounds_pad: float = 1e-3
    """The bounds are grown by this much for the ray clipping."""
    near: float = 0.0
    """METRES from the camera before which :func:`render` ignores surfaces."""
    far: float = math.inf
    """METRES from the camera beyond which :func:`render` ignores surfaces."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """RGB of pixels that hit nothing."""
    chunk: int = WAVEFRONT
    """Rays marching at once (a ray that stops makes room for the next waiting one; see
    :func:`trace`), and points shaded per batch: bounds the working memory."""
    check_camera: bool = True
    """:func:`render` refuses a camera whose centre is inside matter."""
    cone_tile: int = 3
    """Pixels per side of the square tiles whose rays :func:`render_many` first marches as one
    cone (:func:`cone_starts`): each pixel's ray then starts where its tile's cone came near a
    surface, not at the camera. 0 or 1: every ray marches from the camera. The cones of small
    tiles cost more, those of large tiles stop sooner (docs/decisions/rendering-speed.md)."""

    def __post_init__(self) -> None:
        if self.max_steps < 1 or self.max_refine < 0 or self.chunk < 1:
            raise ValueError("max_steps and chunk must be >= 1 and max_refine >= 0")
        if not 0.0 < self.omega < 2.0:
            raise ValueError(f"omega must be in (0, 2), got {self.omega}")
        if not (self.tol > 0 and self.min_step >= 0 and self.footprint_fraction >= 0):
            raise ValueError("tol must be > 0, min_step and footprint_fraction >= 0")
        if self.refine not in REFINE_METHODS:
            raise ValueError(f"refine must be one of {REFINE_METHODS}, got {self.refine!r}")
        if self.grid_resolution < 0 or not self.grid_lipschitz > 0 or not self.grid_skip_cells > 0:
            raise ValueError("need grid_resolution >= 0, grid_lipschitz > 0, grid_skip_cells > 0")
        if not (0 <= self.near < self.far) or self.bounds_pad < 0:
            raise ValueError(
                f"need 0 <= near < far and bounds_pad >= 0, got {self.near}, {self.far}"
            )
        if len(self.background) != 3:
            raise ValueError(f"background must be RGB, got {self.background!r}")
        if isinstance(self.cone_tile, bool) or int(self.cone_tile) != self.cone_tile or self.cone_tile < 0:
            raise ValueError(f"cone_tile must be an integer >= 0, got {self.cone_tile!r}")

    @staticmethod
    def plain() -> SphereTracerConfig:
        """Textbook sphere tracing: unrelaxed steps, no skipping, bisection (a reference)."""
        return SphereTracerConfig(omega=1.0, adaptive=False, grid_resolution=0, refine="bisection")


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


class TraceHits(NamedTuple):
    """What :func:`trace` found for each of ``n`` rays (field frame)."""

    hit: torch.Tensor
    """(n,) bool."""
    t: torch.Tensor
    """(n,) float: field units along the unit direction to the hit; +inf where missed."""
    points: torch.Tensor
    """(n, 3) float: hit points; 0 where missed."""
    winner: torch.Tensor
    """(n,) int64: component hit (0 scene or plain field, i instance), -1 where missed."""
    evals: torch.Tensor
    """(n,) int64: field evaluations (composite costs included), refinement included."""
    lookups: torch.Tensor
    """(n,) int64: distance-grid look-ups."""


def _sample_checked(field: Field, p: torch.Tensor) -> FieldSample:
    s = field.evaluate(p)
    bad = ~torch.isfinite(s.sdf)
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"field {field.name or type(field).__name__!r} returned a non-finite SDF "
            f"({float(s.sdf[k])}) at {int(bad.sum())} of {p.shape[0]} points while tracing, "
            f"for example at field-frame point {p[k].tolist()}"
        )
    return s


@torch.no_grad()
def trace(
    field: Field,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    config: SphereTracerConfig = SphereTracerConfig(),
    grid: DistanceGrid | None = None,
    pixel_angle: float | torch.Tensor = 0.0,
    t_min: torch.Tensor | None = None,
    t_max: torch.Tensor | None = None,
) -> TraceHits:
    """Intersect rays with the zero level set of ``field`` (see the module).

    Parameters
    ----------
    field : Field
        Any field: what is traced is :meth:`~regnf.neural_fields.field.Field.evaluate`, so a
        :class:`~regnf.compositor.composite_field.CompositeField` also reports the winning
        component and its per-point evaluation cost.
    origins : (n, 3) float
        Field frame.
    dirs : (n, 3) float
        Unit directions, field frame.
    config : SphereTracerConfig
        Its ``near`` and ``far`` (METRES, like every length a user sets) bound the search; they
        are brought to field units by ``field.world_scale`` here.
    grid : DistanceGrid, optional
        Built from ``field``; built here (once per call) if None and
        ``config.grid_resolution > 0``. Pass one to amortise it over many calls.
    pixel_angle : float or (n,) float
        Radians per pixel (per ray: rays of several cameras), for the footprint-relative
        tolerance; 0 disables it.
    t_min : (n,) float, optional
        Field units: each ray's march starts no nearer than this, the part before it known to
        be free of surfaces (:func:`cone_starts`).
    t_max : (n,) float, optional
        Field units: each ray's march stops no farther than this (a part of the field it is
        not to see lies beyond).

    Returns
    -------
    TraceHits
        On the field's device.
    """
    near, far = config.near / field.world_scale, config.far / field.world_scale
    check_rays(origins, dirs, near, far, unit=True)
    if grid is None and config.grid_resolution > 0:
        grid = DistanceGrid.build(
            field, config.grid_resolution, config.grid_lipschitz, config.chunk
        )
    dev = field.device
    o, d = origins.to(dev), dirs.to(dev)
    angle = torch.as_tensor(pixel_angle, dtype=o.dtype, device=dev)
    if angle.ndim > 1 or (angle.ndim == 1 and angle.shape[0] != o.shape[0]):
        raise ValueError(f"pixel_angle must be a float or ({o.shape[0]},), got shape {tuple(angle.shape)}")
    if t_min is not None and tuple(t_min.shape) != (o.shape[0],):
        raise ValueError(f"t_min must be ({o.shape[0]},), got shape {tuple(t_min.shape)}")
    t_start, t_stop = _clip(field, o, d, near, far, config)
    if t_max is not None and tuple(t_max.shape) != (o.shape[0],):
        raise ValueError(f"t_max must be ({o.shape[0]},), got shape {tuple(t_max.shape)}")
    if t_min is not None:
        t_start = torch.maximum(t_start, t_min.to(device=dev, dtype=t_start.dtype))
    if t_max is not None:
        t_stop = torch.minimum(t_stop, t_max.to(device=dev, dtype=t_stop.dtype))
    return _trace_wavefront(field, o, d, t_start, t_stop, config, grid, angle.expand(o.shape[0]))


def _clip(field: Field, o: torch.Tensor, d: torch.Tensor, near: float, far: float,
          cfg: SphereTracerConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Where rays ``o``, ``d`` (n, 3) start and stop (n,) each: their span in the field's bounds
    (grown by ``cfg.bounds_pad``) and in ``[near, far]`` (field units)."""
    lo = field.bounds[0].to(o.dtype) - cfg.bounds_pad
    hi = field.bounds[1].to(o.dtype) + cfg.bounds_pad
    t_in, t_out = ray_aabb(o, d, lo, hi)
    return t_in.clamp(min=near), t_out.clamp(max=far)


def _trace_wavefront(
    field: Field,
    o: torch.Tensor,
    d: torch.Tensor,
    t_start: torch.Tensor,
    t_stop: torch.Tensor,
    cfg: SphereTracerConfig,
    grid: DistanceGrid | None,
    pixel_angle: torch.Tensor,
) -> TraceHits:
    """Trace every ray of ``o``, ``d`` (n, 3) over ``[t_start, t_stop]`` (n,) with at most
    ``cfg.chunk`` of them marching at once."""
    n, dev = o.shape[0], o.device
    fp = cfg.footprint_fraction * pixel_angle  # (n,): tolerance per unit of t

    # Per ray, written once when the ray stops marching.
    t = t_start.clone()
    hit = torch.zeros(n, dtype=torch.bool, device=dev)
    bracketed = torch.zeros_like(hit)
    t_prev, r_prev = t_start.clone(), torch.zeros_like(t)  # a bracket's outside end
    s_neg = torch.zeros_like(t)  # SDF at a bracket's inside end (its t)
    evals = torch.zeros(n, dtype=torch.long, device=dev)
    lookups, winner = evals.clone(), evals - 1
    skip_min = cfg.grid_skip_cells * float(grid.cell.min()) if grid is not None else math.inf

    # The marching rays' state, compacted (column k is ray ids[k]; rows of one dtype stacked, so
    # that dropping the stopped rays is three selections, not one per quantity). A wavefront:
    # the rays march cfg.chunk at a time, and each ray that stops makes room for the next
    # waiting one. The field is then evaluated in batches of about that size until the queue
    # is empty, and the long tail of slow rays (grazing an outline), whose steps cost the
    # loop's fixed overhead for a few points each, is paid once per call, not once per chunk.
    queue = (t_start <= t_stop).nonzero().squeeze(1)
    admitted = 0
    ids = queue[:0]
    F = torch.empty(_F_ROWS, 0, dtype=t.dtype, device=dev)
    # SAFE: the ray has a known free sphere (TP, RP); FROM_EVAL: that sphere comes from an
    # evaluation, not the grid; RELAXED: the last step was longer than the safe radius.
    B = torch.zeros(3, 0, dtype=torch.bool, device=dev)
    L = torch.zeros(_L_ROWS, 0, dtype=torch.long, device=dev)  # evaluations, look-ups, winner, first step

    for it in itertools.count():
        room = min(cfg.chunk - ids.numel(), queue.numel() - admitted)
        if room > 0:
            new = queue[admitted:admitted + room]
            admitted += room
            Fn = torch.empty(_F_ROWS, room, dtype=t.dtype, device=dev)
            Fn[_O] = o[new].T
            Fn[_D] = d[new].T
            Fn[_T], Fn[_TE], Fn[_TP] = t_start[new], t_stop[new], t_start[new]
            Fn[_RP] = 0.0
            Fn[_SLOPE] = math.nan  # -d(sdf)/dt between the last two evaluations
            Fn[_CAP] = cfg.omega  # relaxation cap; shrinks after each failed step
            Fn[_FP] = fp[new]
            Ln = torch.zeros(_L_ROWS, room, dtype=torch.long, device=dev)
            Ln[_WIN] = -1
            Ln[_FIRST] = it
            ids, F = torch.cat((ids, new)), torch.cat((F, Fn), 1)
            B = torch.cat((B, torch.zeros(3, room, dtype=torch.bool, device=dev)), 1)
            L = torch.cat((L, Ln), 1)
        if ids.numel() == 0:
            break
        T, TE, TP, RP, SLOPE, CAP = F[_T], F[_TE], F[_TP], F[_RP], F[_SLOPE], F[_CAP]
        SAFE, FROM_EVAL, RELAXED = B[0], B[1], B[2]
        p = (F[_O] + T * F[_D]).T.contiguous()
        skip = None
        if grid is not None:
            lb = grid.lower_bound(p)
            L[_LK] += 1
            # A point reached by a relaxed (unverified) step may lie beyond a thin surface the
            # step jumped over: its free sphere proves nothing about the segment behind it
            # unless it overlaps the last safe sphere (Keinert's test, with the bound as |r|).
            # Otherwise the point is evaluated, and the failure test below sends it back.
            skip = (lb >= skip_min) & (~RELAXED | (RP + lb >= T - TP))
        r = torch.zeros_like(T)
        ei = (~skip).nonzero().squeeze(1) if skip is not None else None
        if ei is None or ei.numel() == ids.numel():
            ei = None
            sample = _sample_checked(field, p)
            r = sample.sdf.to(T.dtype)
            L[_EV] += sample.evals
            L[_WIN] = sample.winner
        elif ei.numel() > 0:
            sample = _sample_checked(field, p[ei])
            r[ei] = sample.sdf.to(T.dtype)
            L[_EV, ei] += sample.evals
            L[_WIN, ei] = sample.winner
        evaluated = ~skip if skip is not None else torch.ones_like(SAFE)

        # Keinert's test: the relaxed step left the union of the two unbounding spheres.
        fail = evaluated & RELAXED & (RP + r.abs() < T - TP)
        if cfg.bracket_on_sign_change:
            fail &= r >= 0  # a sign change is a bracket: refine it rather than go back
        ok = evaluated & ~fail
        close = ok & (r.abs() < _tolerance(T, F[_FP], cfg))  # within tolerance on either side
        neg = ok & (r < 0) & ~close
        crossed = neg & SAFE
        stops_on_hit = close | (neg & ~SAFE)
        move = ok & ~neg & ~close
        # A hit within tolerance is still off by r / cos(incidence) along the ray; one
        # secant (Newton) step with the slope measured between the last two samples
        # removes most of that for free. Skipped where the slope is unknown or grazing.
        good = torch.isfinite(SLOPE) & (SLOPE > MIN_NEWTON_SLOPE)
        t_hit = torch.where(good, T + r / SLOPE.clamp(min=MIN_NEWTON_SLOPE), T)
        # A move: the sample is a safe sphere; the next step is relaxed by the measured slope.
        dt = T - TP
        slope = torch.where(FROM_EVAL & (dt > 0), (RP - r) / dt.clamp(min=1e-30), SLOPE)
        w = _relaxation(CAP, slope, cfg)
        relax_next = (w > 1.0) & (w * r > cfg.min_step)
        t_next = T + (w * r).clamp(min=cfg.min_step)
        # A relaxed step past the exit is unverified: take the plain one there instead.
        beyond = t_next > TE
        t_next = torch.where(beyond, T + r.clamp(min=cfg.min_step), t_next)
        relax_next &= ~beyond
        # A failed step goes back to the plain one from the last safe point.
        t_back = TP + RP.clamp(min=cfg.min_step)
        cap_back = 1.0 + 0.5 * (CAP - 1.0) if cfg.adaptive else torch.ones_like(CAP)

        t_new = torch.where(move, t_next, torch.where(fail, t_back, torch.where(close, t_hit, T)))
        F[_TP] = torch.where(move, T, TP)
        F[_RP] = torch.where(move, r, RP)
        F[_SLOPE] = torch.where(move, slope, SLOPE)
        F[_CAP] = torch.where(fail, cap_back, CAP)
        B[2] = torch.where(move, relax_next, RELAXED & ~fail)
        B[1] = FROM_EVAL | move
        B[0] = SAFE | move
        goes_on = fail | (move & (t_new <= TE))
        if skip is not None:
            # A grid step is an unrelaxed step in guaranteed free space: a safe sphere.
            t_new = torch.where(skip, T + lb, t_new)
            F[_TP] = torch.where(skip, T, F[_TP])
            F[_RP] = torch.where(skip, lb, F[_RP])
            F[_SLOPE] = torch.where(skip, math.nan, F[_SLOPE])  # no SDF value: no slope
            B[0] |= skip
            B[1] &= ~skip
            B[2] &= ~skip
            goes_on |= skip & (t_new <= TE)
        F[_T] = t_new

        stops, keep = ~goes_on, goes_on
        if it + 1 >= cfg.max_steps:  # no ray has taken max_steps steps before this iteration
            # Out of steps: a miss (``hit`` and ``bracketed`` are False for a ray that goes on).
            stops = stops | (it + 1 - L[_FIRST] >= cfg.max_steps)
            keep = ~stops
        if bool(stops.any()):
            si = ids[stops]
            t[si], hit[si], bracketed[si] = t_new[stops], stops_on_hit[stops], crossed[stops]
            t_prev[si], r_prev[si], s_neg[si] = F[_TP, stops], F[_RP, stops], r[stops]
            evals[si], lookups[si], winner[si] = L[_EV, stops], L[_LK, stops], L[_WIN, stops]
            ids, F, B, L = ids[keep], F[:, keep], B[:, keep], L[:, keep]

    bi = bracketed.nonzero().squeeze(1)
    if bi.numel() > 0:
        t[bi] = _refine(field, o, d, t_prev, r_prev, t, s_neg, bi, cfg, fp, evals, winner)
        hit[bi] = True

    t = torch.where(hit, t, torch.full_like(t, math.inf))
    winner = torch.where(hit, winner, torch.full_like(winner, BACKGROUND_ID))
    points = torch.where(
        hit[:, None], o + t.nan_to_num(posinf=0.0)[:, None] * d, torch.zeros_like(o)
    )
    return TraceHits(hit, t, points, winner, evals, lookups)


_O, _D = slice(0, 3), slice(3, 6)
_T, _TE, _TP, _RP, _SLOPE, _CAP, _FP = 6, 7, 8, 9, 10, 11, 12
_F_ROWS = 13
"""Rows of the marching rays' float state: origin, direction (3 each), t, exit t, the last
safe point's t and radius, the SDF's slope along the ray, the relaxation cap, the hit
tolerance per unit of t (the pixel's footprint fraction)."""
_EV, _LK, _WIN, _FIRST = 0, 1, 2, 3
_L_ROWS = 4
"""Rows of their integer state: field evaluations, grid look-ups, winning component, the
iteration of the ray's first step."""


def _tolerance(t: torch.Tensor, fp: torch.Tensor, cfg: SphereTracerConfig) -> torch.Tensor:
    """The hit tolerance at distances ``t`` of rays whose tolerance per unit of t is ``fp``: a
    fraction of the pixel's footprint, at least ``cfg.tol``."""
    return (fp * t).clamp(min=cfg.tol)


def _relaxation(cap: torch.Tensor, slope: torch.Tensor, cfg: SphereTracerConfig) -> torch.Tensor:
    """Step factors (m,) of rays with relaxation caps ``cap`` and SDF slopes ``slope`` (m,).

    If the SDF falls along the ray at rate ``m`` (a plane seen at incidence cosine ``m``),
    a step ``w r`` keeps the unbounding spheres overlapping iff ``w <= 2 / (1 + m)``; a
    margin below that bound avoids borderline failures. Unknown slopes (NaN) use the cap.
    """
    if not cfg.adaptive:
        return cap
    m = slope.clamp(0.0, 1.0)
    w = (ADAPTIVE_MARGIN * 2.0 / (1.0 + m)).clamp(min=1.0)
    return torch.where(torch.isnan(slope), cap, torch.minimum(w, cap))


def _refine(
    field: Field,
    o: torch.Tensor,
    d: torch.Tensor,
    t_pos: torch.Tensor,
    s_pos: torch.Tensor,
    t_neg: torch.Tensor,
    s_neg: torch.Tensor,
    bi: torch.Tensor,
    cfg: SphereTracerConfig,
    fp: torch.Tensor,
    evals: torch.Tensor,
    winner: torch.Tensor,
) -> torch.Tensor:
    """Roots (len(bi),) of the brackets ``[t_pos (sdf > 0), t_neg (sdf < 0)]`` of rays ``bi``.

    Illinois false position: the secant point of the bracket, halving the value kept at an
    end that survives twice in a row (so that convex SDF profiles converge fast too). ``fp``
    (n,) is every ray's tolerance per unit of t; ``evals`` and ``winner`` are updated in place.
    """
    a, sa = t_pos[bi].clone(), s_pos[bi].clone()
    b, sb = t_neg[bi].clone(), s_neg[bi].clone()
    root = b.clone()
    last = torch.zeros_like(a)  # +1: a moved last time, -1: b moved, 0: neither yet
    act = torch.arange(bi.numel(), device=a.device)  # positions in bi still refining
    for _ in range(cfg.max_refine):
        if act.numel() == 0:
            break
        aa, bb = a[act], b[act]
        mid = 0.5 * (aa + bb)
        if cfg.refine == "illinois":
            m = aa + (bb - aa) * sa[act] / (sa[act] - sb[act])
            # Safeguard: a secant point outside the open bracket falls back to the midpoint.
            m = torch.where(torch.isfinite(m) & (m > aa) & (m < bb), m, mid)
        else:
            m = mid
        rays = bi[act]
        s = _sample_checked(field, o[rays] + m[:, None] * d[rays])
        r = s.sdf.to(a.dtype)
        evals[rays] += s.evals
        winner[rays] = s.winner
        tol = _tolerance(m, fp[rays], cfg)
        done = (r.abs() < tol) | (bb - aa < tol)
        root[act[done]] = m[done]
        outside = ~done & (r > 0)
        inside = ~done & ~outside
        ao, bo = act[outside], act[inside]
        a[ao], sa[ao] = m[outside], r[outside]
        sb[ao] = torch.where(last[ao] > 0, 0.5 * sb[ao], sb[ao])
        last[ao] = 1.0
        b[bo], sb[bo] = m[inside], r[inside]
        sa[bo] = torch.where(last[bo] < 0, 0.5 * sa[bo], sa[bo])
        last[bo] = -1.0
        act = act[~done]
    if act.numel() > 0:  # unconverged: one secant estimate, no further evaluation
        frac = (sa[act] / (sa[act] - sb[act])).nan_to_num(0.5).clamp(0.0, 1.0)
        root[act] = a[act] + frac * (b[act] - a[act])
    return root


CONE_MARGIN = 0.98
"""Fraction of a cone step's proven free length that the cone takes (room for rounding)."""


@torch.no_grad()
def cone_starts(
    field: Field,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    tiles: torch.Tensor,
    config: SphereTracerConfig = SphereTracerConfig(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each ray's march may start: its tile's rays marched as one cone, for one
    evaluation a step instead of one a ray.

    The rays of a tile leave one apex within ``c = 2 sin(theta / 2)`` (the chord of the
    largest angle ``theta`` between a ray and the tile's mean direction, the axis). If the
    field is ``r`` at the axis point ``t``, every ray of the tile is free of surfaces from
    ``t`` to ``t + (r - t c) / (1 + c)``: a point ``s`` along a ray lies within
    ``s c + (s - t)`` of that axis point. The cone steps so, from the nearest start of its
    rays (:func:`trace`'s clipping), and stops where its step becomes shorter than its width
    there, ``t c``, where its axis leaves the bounds, or after ``config.max_steps`` steps.
    Like the tracer's own steps, this takes the field's value as a distance bound, scaled by
    ``omega`` where that is below 1. Outside the bounds, which hold every surface, the bound
    at a point ``e`` away from them is ``hypot(e, r)``, with ``r`` the field's bound at their
    nearest point.

    Parameters
    ----------
    field : Field
    origins, dirs : (n, 3) float
        The rays, field frame, unit directions.
    tiles : (n,) int
        Each ray's tile, 0 to m - 1; a tile whose rays do not share an origin is not marched.
    config : SphereTracerConfig
        ``near`` and ``far`` in metres, as for :func:`trace`.

    Returns
    -------
    t_min : (n,) float
        Field units: the ray's march may start here (``-inf`` where its tile was not marched).
    evals : (m,) int
        Field evaluations each tile's cone took (composite costs included).
    """
    near, far = config.near / field.world_scale, config.far / field.world_scale
    dev = field.device
    o, d, tiles = origins.to(dev), dirs.to(dev), tiles.to(device=dev, dtype=torch.long)
    m = int(tiles.max()) + 1 if tiles.numel() else 0
    start, _ = _clip(field, o, d, near, far, config)
    axis = torch.zeros(m, 3, dtype=d.dtype, device=dev).index_add_(0, tiles, d)
    axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True).clamp(min=1e-30)
    cos = (d * axis[tiles]).sum(-1).clamp(-1.0, 1.0)
    cos_min = torch.ones(m, dtype=d.dtype, device=dev).scatter_reduce(0, tiles, cos, "amin")
    chord = torch.sqrt(2.0 * (1.0 - cos_min)) + 1e-6  # 2 sin(theta / 2), and a margin for rounding
    apex = torch.zeros(m, 3, dtype=o.dtype, device=dev).index_copy_(0, tiles, o)
    spread = torch.zeros(m, dtype=o.dtype, device=dev).scatter_reduce(
        0, tiles, torch.linalg.vector_norm(o - apex[tiles], dim=-1), "amax")
    t = torch.full((m,), math.inf, dtype=o.dtype, device=dev).scatter_reduce(0, tiles, start, "amin")
    _, a_out = _clip(field, apex, axis, -math.inf, far, config)
    marched = (spread == 0) & (cos_min > 0) & torch.isfinite(t)
    lo, hi = field.bounds[0].to(o.dtype), field.bounds[1].to(o.dtype)
    evals = torch.zeros(m, dtype=torch.long, device=dev)
    trust = min(1.0, config.omega)
    act = marched.nonzero().squeeze(1)
    for _ in range(config.max_steps):
        if act.numel() == 0:
            break
        ta, ca = t[act], chord[act]
        p = apex[act] + ta[:, None] * axis[act]
        # Every surface lies in the bounds, a convex box: from a point p outside them, with q
        # its nearest point of the box, every surface point s has |p - s|^2 >= |p - q|^2 +
        # |q - s|^2. So the cone of a camera outside the bounds enters them without stopping
        # at their face.
        q = torch.maximum(torch.minimum(p, hi), lo)
        out = torch.linalg.vector_norm(p - q, dim=-1)
        sample = _sample_checked(field, q)
        evals[act] += sample.evals
        r = torch.hypot(out, trust * sample.sdf.to(out.dtype).clamp(min=0.0))
        step = CONE_MARGIN * (r - ta * ca) / (1.0 + ca)
        t[act] = ta + step.clamp(min=0.0)
        act = act[(step > ta * ca) & (t[act] <= a_out[act])]
    t = torch.where(marched, t, torch.full_like(t, -math.inf))
    return t[tiles], evals


def pixel_tiles(width: int, height: int, tile: int, device: torch.device | str | None = None) -> torch.Tensor:
    """(height width,) int64: the tile of each pixel (row-major) in square tiles of ``tile``
    pixels a side, numbered row-major from 0 (the last row and column of tiles may be smaller)."""
    columns = -(-int(width) // tile)
    v = torch.arange(int(height), device=device) // tile
    u = torch.arange(int(width), device=device) // tile
    return (v[:, None] * columns + u[None, :]).reshape(-1)


@torch.no_grad()
def render(
    field: Field,
    camera: Camera,
    config: SphereTracerConfig = SphereTracerConfig(),
    grid: DistanceGrid | None = None,
) -> Render:
    """Sphere-trace one view of ``field`` from ``camera`` (posed in the field's metres).

    Raises ``ValueError`` if the camera centre is inside matter (``config.check_camera``)
    or the field returns non-finite values. A view with no surface is not an error: every
    pixel is background (``mask`` all False, ``instance_id`` -1, depth 0).

    Parameters
    ----------
    field : Field
    camera : Camera
    config : SphereTracerConfig
        ``near`` and ``far`` in metres; the other distances in field units.
    grid : DistanceGrid, optional
        Prebuilt for ``field``; see :func:`trace`.

    Returns
    -------
    Render
        ``evals_per_pixel`` counts tracing only (shading adds one SDF gradient and one
        colour query per hit pixel).
    """
    return render_many(field, [camera], config, grid)[0]


@torch.no_grad()
def render_many(
    field: Field,
    cameras: Sequence[Camera],
    config: SphereTracerConfig = SphereTracerConfig(),
    grid: DistanceGrid | None = None,
    normals: bool = True,
) -> list[Render]:
    """Sphere-trace several views of ``field`` in one wavefront: :func:`render` of each camera.

    The rays of every view march together (``config.chunk`` at a time), so the slow rays at
    the end of a trace, few points a step, are traced once for all views instead of once a
    view: on one thread, 8 views of a variant of the demo's baked composite in 4.15 s instead of
    4.25 s, and the demo's 6 substitution views in two batches of 3 on two threads in 6.7 s
    instead of 7.4 s (:attr:`regnf.compositor.render_folder.RenderConfig.views_per_trace`).
    A ray's trace is its own, so the images are those of :func:`render` up to the last bits
    of a network's batched evaluation (exactly the same on a baked field).

    Parameters
    ----------
    field : Field
    cameras : sequence of Camera
        Each with its own size and intrinsics.
    config : SphereTracerConfig
    grid : DistanceGrid, optional
        Prebuilt for ``field``; see :func:`trace`.
    normals : bool
        Compute the normals (an SDF gradient at every hit); False leaves ``Render.normals``
        None, for callers that keep colour, depth and ids only (a tenth of a baked variant's
        time, the gradient of the composite at every hit).

    Returns
    -------
    list of Render
        One per camera, in order.
    """
    if not cameras:
        return []
    rays = [camera_rays(field, camera) for camera in cameras]
    if config.check_camera:
        for r in rays:
            check_camera_outside(field, r.origin)
    angles = torch.cat([torch.full_like(r.z_scale, r.pixel_angle) for r in rays])
    origins, dirs = torch.cat([r.origins for r in rays]), torch.cat([r.dirs for r in rays])
    t_min, cone_evals = None, None
    if config.cone_tile > 1:
        k, tiles, first = config.cone_tile, [], 0
        for camera in cameras:  # every camera's tiles numbered after the previous camera's
            tiles.append(first + pixel_tiles(camera.width, camera.height, k, field.device))
            first += -(-camera.width // k) * -(-camera.height // k)
        tiles = torch.cat(tiles)
        t_min, tile_evals = cone_starts(field, origins, dirs, tiles, config)
        # Each tile's cone counted on its first ray, so that sums and means over pixels hold them.
        ray_ids = torch.arange(len(tiles), device=tiles.device)
        first_ray = torch.full_like(tile_evals, len(tiles)).scatter_reduce(0, tiles, ray_ids, "amin")
        cone_evals = torch.zeros_like(tiles)
        cone_evals[first_ray] = tile_evals
    hits = trace(field, origins, dirs, config, grid, angles, t_min)
    if cone_evals is not None:
        hits = hits._replace(evals=hits.evals + cone_evals)
    renders, start = [], 0
    for camera, r in zip(cameras, rays, strict=True):
        end = start + r.z_scale.shape[0]
        view = TraceHits(*(x[start:end] for x in hits))
        renders.append(_to_render(field, camera, r, view, config.background, config.chunk, normals))
        start = end
    return renders


def _to_render(
    field: Field,
    camera: Camera,
    rays: CameraRays,
    hits: TraceHits,
    background: Sequence[float],
    chunk: int,
    normals: bool,
) -> Render:
    h, w = camera.height, camera.width
    shaded = shade_hits(field, hits.points, rays.dirs, hits.hit, background, chunk, normals)
    depth = torch.where(
        hits.hit, hits.t.nan_to_num(posinf=0.0) * rays.z_scale * field.world_scale, 0.0
    )
    return Render(
        rgb=shaded.rgb.reshape(h, w, 3),
        depth=depth.reshape(h, w),
        normals=None if shaded.normals is None else shaded.normals.reshape(h, w, 3),
        instance_id=hits.winner.reshape(h, w),
        mask=hits.hit.reshape(h, w),
        evals_per_pixel=hits.evals.reshape(h, w),
        lookups_per_pixel=hits.lookups.reshape(h, w),
    )
