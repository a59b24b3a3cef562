"""Views of a field by sphere tracing: :func:`render` and :func:`render_many` on the one tracer
(:func:`regnf.render.sphere_tracer.trace`).

:func:`render_many` first marches the rays of
each square tile of pixels (``cone_tile``) as one cone, one evaluation a step for the tile
(:func:`cone_starts`): the tile's rays then start where its cone came near a surface, at a
point proven free, instead of at the camera. The free space before the first surface is
crossed once a tile, not once a ray (docs/decisions/rendering-speed.md). A ray's result is
still its own trace's, from a later start: the same surfaces to the tracer's tolerance, not the
same bits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from regnf.core.render_result import Render
from regnf.fields.distance_grid import DistanceGrid
from regnf.fields.field import Field
from regnf.fields.shading import check_camera_outside, shade_hits
from regnf.render.camera import Camera, CameraRays, camera_rays
from regnf.render.sphere_tracer import (
    SphereTracerConfig,
    TraceHits,
    clip_to_bounds,
    sample_checked,
    trace,
)

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
    start, _ = clip_to_bounds(field, o, d, near, far, config)
    axis = torch.zeros(m, 3, dtype=d.dtype, device=dev).index_add_(0, tiles, d)
    axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True).clamp(min=1e-30)
    cos = (d * axis[tiles]).sum(-1).clamp(-1.0, 1.0)
    cos_min = torch.ones(m, dtype=d.dtype, device=dev).scatter_reduce(0, tiles, cos, "amin")
    chord = torch.sqrt(2.0 * (1.0 - cos_min)) + 1e-6  # 2 sin(theta / 2), and a margin for rounding
    apex = torch.zeros(m, 3, dtype=o.dtype, device=dev).index_copy_(0, tiles, o)
    spread = torch.zeros(m, dtype=o.dtype, device=dev).scatter_reduce(
        0, tiles, torch.linalg.vector_norm(o - apex[tiles], dim=-1), "amax")
    t = torch.full((m,), math.inf, dtype=o.dtype, device=dev).scatter_reduce(0, tiles, start, "amin")
    _, a_out = clip_to_bounds(field, apex, axis, -math.inf, far, config)
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
        sample = sample_checked(field, q)
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
    view (docs/decisions/rendering-speed.md;
    :attr:`regnf.compositor.render_folder.RenderConfig.views_per_trace`).
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
