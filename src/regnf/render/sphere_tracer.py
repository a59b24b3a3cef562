"""The one sphere tracer: of any field, with a composite's extra outputs.

Per ray (vectorised over rays; the loops are over STEPS, each touching only the rays still
active):

1. Rays are clipped to the field's bounds (and ``[near, far]``).
2. Empty-space skipping: where the coarse :class:`~regnf.fields.distance_grid.DistanceGrid`
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
   A relaxed step that lands inside matter without that overlap is not a bracket: a thin
   surface in the unverified gap, in front of a thicker one, could be skipped in favour of
   the one behind it.
4. A sample with ``|sdf| < tol(t)`` is a hit, with ``tol(t) = max(tol,
   footprint_fraction * t * pixel_angle)``: never finer than a fraction of the pixel
   footprint. Its ``t`` then gets one free secant correction ``r / m`` (``m`` the slope
   above), which removes most of the ``tol / cos(incidence)`` depth error. A sign change (a relaxed or minimum step crossed the surface) is bracketed
   and refined by Illinois false position (or plain bisection) to ``|sdf| < tol(t)``.

Views are rendered by :mod:`regnf.render.sphere_render`, which starts each ray where a
cone of its tile came near a surface.

A ray whose first sample is inside matter (the bounds or ``near`` cut through an object)
is a hit at its start; a ray that leaves the bounds (or ``far``) or runs out of
``max_steps`` is a miss. Non-finite SDF values are an error, not a miss.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import torch

from regnf.core.cameras import ray_aabb
from regnf.core.errors import RegnfError
from regnf.fields.distance_grid import DistanceGrid
from regnf.fields.field import DEFAULT_CHUNK, Field, FieldSample

Rays = TypeVar("Rays", bound=tuple)
"""A named tuple of per-ray tensors (first dimension: the ray)."""
BACKGROUND_ID = -1
"""Instance id (winner) of a ray or pixel that hit nothing."""

WAVEFRONT = DEFAULT_CHUNK
"""Rays marching at once by default (65536). Smaller batches pay the loop's fixed cost more
often, larger ones miss the caches, and a view split over two batches takes more steps
(docs/decisions/rendering-speed.md)."""
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
    """Relaxation factor of the steps (cap when adaptive), in (0, 2): > 1 over-, 1 plain, < 1 under-relaxed."""
    adaptive: bool = True
    """Adapt the relaxation to the SDF's slope along the ray (the module); False: Keinert's fixed ``omega``."""
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
    """Rays marching at once and points shaded per batch (:data:`WAVEFRONT`): bounds the working memory."""
    check_camera: bool = True
    """:func:`render` refuses a camera whose centre is inside matter."""
    cone_tile: int = 3
    """Side of the tiles first marched as cones, pixels; 0 or 1: no cones (docs/decisions/rendering-speed.md)."""

    def __post_init__(self) -> None:
        if self.max_steps < 1 or self.max_refine < 0 or self.chunk < 1:
            raise RegnfError("max_steps and chunk must be >= 1 and max_refine >= 0")
        if not 0.0 < self.omega < 2.0:
            raise RegnfError(f"omega must be in (0, 2), got {self.omega}")
        if not (self.tol > 0 and self.min_step >= 0 and self.footprint_fraction >= 0):
            raise RegnfError("tol must be > 0, min_step and footprint_fraction >= 0")
        if self.refine not in REFINE_METHODS:
            raise RegnfError(f"refine must be one of {REFINE_METHODS}, got {self.refine!r}")
        if self.grid_resolution < 0 or not self.grid_lipschitz > 0 or not self.grid_skip_cells > 0:
            raise RegnfError("need grid_resolution >= 0, grid_lipschitz > 0, grid_skip_cells > 0")
        if not (0 <= self.near < self.far) or self.bounds_pad < 0:
            raise RegnfError(
                f"need 0 <= near < far and bounds_pad >= 0, got {self.near}, {self.far}"
            )
        if len(self.background) != 3:
            raise RegnfError(f"background must be RGB, got {self.background!r}")
        if isinstance(self.cone_tile, bool) or int(self.cone_tile) != self.cone_tile or self.cone_tile < 0:
            raise RegnfError(f"cone_tile must be an integer >= 0, got {self.cone_tile!r}")

    @staticmethod
    def plain() -> SphereTracerConfig:
        """Textbook sphere tracing: unrelaxed steps, no skipping, bisection (a reference)."""
        return SphereTracerConfig(omega=1.0, adaptive=False, grid_resolution=0, refine="bisection")


def check_rays(origins: torch.Tensor, dirs: torch.Tensor, near: float, far: float,
               unit: bool = False) -> None:
    """Raise ``ValueError`` unless ``origins``, ``dirs`` are both (n, 3), ``0 <= near < far``
    and (with ``unit``) every direction has unit length."""
    if origins.ndim != 2 or origins.shape[-1] != 3 or origins.shape != dirs.shape:
        raise RegnfError(
            "origins and dirs must both be (n, 3), got "
            f"{tuple(origins.shape)} and {tuple(dirs.shape)}"
        )
    if not (near >= 0 and far > near):
        raise RegnfError(f"need 0 <= near < far, got near={near}, far={far}")
    if unit and dirs.shape[0] > 0:
        norm_err = float((torch.linalg.vector_norm(dirs, dim=-1) - 1.0).abs().max())
        if not norm_err < 1e-4:
            raise RegnfError(f"dirs must be unit vectors (largest |norm - 1| = {norm_err:.3g})")


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


def sample_checked(field: Field, p: torch.Tensor) -> FieldSample:
    s = field.evaluate(p)
    bad = ~torch.isfinite(s.sdf)
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise RegnfError(
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
        Any field: what is traced is :meth:`~regnf.fields.field.Field.evaluate`, so a
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
        raise RegnfError(f"pixel_angle must be a float or ({o.shape[0]},), got shape {tuple(angle.shape)}")
    if t_min is not None and tuple(t_min.shape) != (o.shape[0],):
        raise RegnfError(f"t_min must be ({o.shape[0]},), got shape {tuple(t_min.shape)}")
    t_start, t_stop = clip_to_bounds(field, o, d, near, far, config)
    if t_max is not None and tuple(t_max.shape) != (o.shape[0],):
        raise RegnfError(f"t_max must be ({o.shape[0]},), got shape {tuple(t_max.shape)}")
    if t_min is not None:
        t_start = torch.maximum(t_start, t_min.to(device=dev, dtype=t_start.dtype))
    if t_max is not None:
        t_stop = torch.minimum(t_stop, t_max.to(device=dev, dtype=t_stop.dtype))
    return _trace_wavefront(field, o, d, t_start, t_stop, config, grid, angle.expand(o.shape[0]))


def clip_to_bounds(field: Field, o: torch.Tensor, d: torch.Tensor, near: float, far: float,
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
            sample = sample_checked(field, p)
            r = sample.sdf.to(T.dtype)
            L[_EV] += sample.evals
            L[_WIN] = sample.winner
        elif ei.numel() > 0:
            sample = sample_checked(field, p[ei])
            r[ei] = sample.sdf.to(T.dtype)
            L[_EV, ei] += sample.evals
            L[_WIN, ei] = sample.winner
        evaluated = ~skip if skip is not None else torch.ones_like(SAFE)

        # Keinert's test: the relaxed step left the union of the two unbounding spheres.
        fail = evaluated & RELAXED & (RP + r.abs() < T - TP)
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
        s = sample_checked(field, o[rays] + m[:, None] * d[rays])
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
