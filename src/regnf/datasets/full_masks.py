"""Whole silhouettes of a variant's objects, hidden parts included: each object traced alone.

A view's own images decide most pixels: where the composite shows the instance, the object
alone is hit too (the composite's first hit is its first); where the view shows no surface,
nothing is hit; where it shows a surface beyond the object's box, the ray crossed the box
and met nothing. Only the other pixels whose ray crosses the object's box in front of the
surface the view shows are traced, each from just before that surface (the object lies
behind it) to where it leaves the box.

Every object's rays go in one trace: the objects stand side by side, each in its own frame,
in a field of lanes (:class:`Lanes`). Each ray is brought into its object's frame (where the
object's own box is tighter than the box around the placed object, and no placement is
applied at every step) and into its lane, and is stopped where it leaves the object's box,
so that it meets no other object. One trace pays the tracer's per-step cost once for all the
objects, not once per object.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import Field, FieldInfo, FieldSample

FULL_MASK_MARGIN = 0.005
"""How far before the surface a view shows a pixel's trace of a hidden object starts, metres
(depth images hold whole millimetres)."""


class Lanes(Field):
    """Fields side by side along x, lane ``k`` moved by ``shifts[k]``: a point is evaluated by
    the field of the lane it lies in.

    Parameters
    ----------
    fields : sequence of Field
        On one device. Each is evaluated in its own units; the lanes' ``to_world`` is the
        first one's, so a trace of them takes each ray's span from its caller (``t_min``,
        ``t_max``), not from ``near`` and ``far``.
    shifts : (k,) float
        Each field's move along x, in its units, increasing; lanes must not overlap.
    """

    def __init__(self, fields: Sequence[Field], shifts: Sequence[float]) -> None:
        lo = torch.stack([f.bounds[0].double() + torch.tensor([s, 0.0, 0.0], dtype=torch.float64, device=f.device)
                          for f, s in zip(fields, shifts, strict=True)])
        hi = torch.stack([f.bounds[1].double() + torch.tensor([s, 0.0, 0.0], dtype=torch.float64, device=f.device)
                          for f, s in zip(fields, shifts, strict=True)])
        if bool((lo[1:, 0] <= hi[:-1, 0]).any()):
            raise RegnfError("lanes overlap: each shift must clear the lane before it")
        super().__init__(torch.stack([lo.min(dim=0).values, hi.max(dim=0).values]), fields[0].to_world,
                         FieldInfo(name="lanes"))
        self.lanes = torch.nn.ModuleList(fields)
        self.shifts = [float(s) for s in shifts]
        # A point belongs to the lane whose box it is nearest along x: cut halfway between them.
        self.register_buffer("cuts", (0.5 * (hi[:-1, 0] + lo[1:, 0])).contiguous())
        self.to(fields[0].device)

    def _dispatch(self, x: torch.Tensor, call: Any) -> list[tuple[torch.Tensor, Any]]:
        """``call(field, points, indices)`` per lane on the points of ``x`` (n, 3) in it (moved
        into the field's own frame), with their indices."""
        lane = torch.bucketize(x[:, 0].contiguous(), self.cuts.to(x.dtype))
        out = []
        for k, field in enumerate(self.lanes):  # a loop over the handful of objects
            idx = (lane == k).nonzero().squeeze(1)
            if idx.numel():
                q = x[idx]  # a copy (indexed by a tensor)
                q[:, 0] -= self.shifts[k]
                out.append((idx, call(field, q, idx)))
        return out

    def evaluate(self, x: torch.Tensor) -> FieldSample:
        """SDF (n,), winner 0 (n,) and evaluations (n,) at points ``x`` (n, 3)."""
        sdf = torch.full((x.shape[0],), float("inf"), dtype=x.dtype, device=x.device)
        evals = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        for idx, s in self._dispatch(x, lambda f, q, _: f.evaluate(q)):  # a loop over lanes
            sdf[idx] = s.sdf.to(sdf.dtype)
            evals[idx] = s.evals.to(evals.dtype)
        return FieldSample(sdf, torch.zeros_like(evals), evals)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3) to the object of their lane."""
        return self.evaluate(x).sdf

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """RGB (n, 3) of points ``x`` (n, 3) from the object of their lane (directions ``d`` (n, 3))."""
        rgb = torch.zeros(x.shape[0], 3, dtype=x.dtype, device=x.device)
        for idx, c in self._dispatch(x, lambda f, q, i: f.color(q, None if d is None else d[i])):  # lanes
            rgb[idx] = c.to(rgb.dtype)
        return rgb


def full_masks(folder: Path, field: Any, cameras: Sequence[Any], sphere: Any) -> dict[int, list[np.ndarray]]:
    """Every instance's whole silhouette in every view (see the module).

    Parameters
    ----------
    folder : Path
        The variant's folder, with its instance and depth images
        (:func:`regnf.compositor.render_folder.view_files`).
    field : CompositeField
        The variant's composite (neural or baked), in the scene field frame.
    cameras : sequence of Camera
        The variant's cameras, room metres.
    sphere : SphereTracerConfig
        The tracer settings the views were rendered with.

    Returns
    -------
    dict int -> list of (h, w) bool
        Instance image id -> its whole silhouette in each view.
    """
    from regnf.compositor.render_folder import view_files
    from regnf.core.cameras import ray_aabb, rays_through
    from regnf.core.image_io import read_depth_png, read_instance_png
    from regnf.render.sphere_tracer import trace

    views = [(read_instance_png(folder / view_files(k).instance), read_depth_png(folder / view_files(k).depth))
             for k in range(len(cameras))]
    ids_of = [int(i) for i in field.instance_ids]
    masks = {iid: [ids == iid for ids, _ in views] for iid in ids_of}
    objects = [p.mapped.child for p in field.placements]
    if not objects:
        return masks
    to_world = field.to_world.detach().cpu().double()
    world_to_field = torch.linalg.inv(to_world)
    scale = float(field.world_scale)  # metres per field unit
    # Each placement x -> s R x + t, object frame to field frame.
    R = torch.stack([p.mapped.rotation.detach().cpu().double() for p in field.placements])  # (k, 3, 3)
    t = torch.stack([p.mapped.translation.detach().cpu().double() for p in field.placements])  # (k, 3)
    s = torch.stack([p.mapped.scale.detach().cpu().double().reshape(()) for p in field.placements])  # (k,)
    # Each object's own box, its frame (an oriented box in the field's), padded as the tracer pads.
    own = torch.stack([o.bounds.detach().cpu().double() for o in objects])  # (k, 2, 3)
    own = own + (sphere.bounds_pad / s)[:, None, None] * torch.tensor([-1.0, 1.0], dtype=torch.float64)[None, :, None]
    # The objects side by side in their own frames, each a gap after the last.
    gap = float((own[:, 1] - own[:, 0]).norm(dim=1).max())
    shifts, edge = [], 0.0
    for lo, hi in own:  # a loop over instances
        shifts.append(0.0 if not shifts else edge + gap - float(lo[0]))
        edge = float(hi[0]) + shifts[-1]
    # The pixels to trace, as (lane, view, rows, columns).
    picked: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    for lane, iid in enumerate(ids_of):  # a loop over instances
        corners = torch.stack(torch.meshgrid(*own[lane].T, indexing="ij"), dim=-1).reshape(-1, 3)
        corners = (s[lane] * corners @ R[lane].T + t[lane]) @ to_world[:3, :3].T + to_world[:3, 3]
        corners = corners.numpy()
        for k, (cam, (ids, depth)) in enumerate(zip(cameras, views, strict=True)):  # a loop over views
            window = box_window(cam, corners)
            if window is None:
                continue
            x0, y0, x1, y1 = window
            # A surface the view shows beyond the whole box: the ray crossed the box and met nothing.
            c2w = np.asarray(cam.camera_to_world, np.float64)
            farthest = float(((corners - c2w[:3, 3]) @ c2w[:3, 2]).max())
            shown = depth[y0:y1, x0:x1]
            rows, cols = np.nonzero((ids[y0:y1, x0:x1] != iid) & (shown > 0) & (shown - FULL_MASK_MARGIN <= farthest))
            if rows.size:
                picked.append((lane, k, rows + y0, cols + x0))
    if not picked:
        return masks
    lane = torch.from_numpy(np.concatenate([np.full(len(r), g) for g, _, r, _ in picked]))
    view = np.concatenate([np.full(len(r), k) for _, k, r, _ in picked])
    rows = np.concatenate([r for _, _, r, _ in picked])
    cols = np.concatenate([c for _, _, _, c in picked])
    n = len(rows)
    o, d = torch.empty(n, 3, dtype=torch.float64), torch.empty(n, 3, dtype=torch.float64)
    z, angle, shown = (torch.empty(n, dtype=torch.float64) for _ in range(3))
    for k, cam in enumerate(cameras):  # a loop over views: each view's rays at once
        at = torch.from_numpy(np.nonzero(view == k)[0])
        if at.numel() == 0:
            continue
        C = world_to_field @ torch.as_tensor(cam.camera_to_world, dtype=torch.float64)
        o[at], d[at], z[at] = rays_through(torch.as_tensor(cam.K, dtype=torch.float64), C,
                                           torch.from_numpy(cols[at] + 0.5), torch.from_numpy(rows[at] + 0.5))
        angle[at] = 1.0 / float(min(cam.K[0, 0], cam.K[1, 1]))
        shown[at] = torch.from_numpy(views[k][1][rows[at], cols[at]].astype(np.float64))
    # The rays in their object's frame, where t is the field's over the object's scale.
    o_own = torch.einsum("ni,nij->nj", o - t[lane], R[lane]) / s[lane, None]
    d_own = torch.einsum("ni,nij->nj", d, R[lane])
    t_in, t_out = ray_aabb(o_own, d_own, own[lane, 0], own[lane, 1])
    # Metres of z-depth to the object's units along the ray, less a margin for the depth's rounding.
    behind = (shown - FULL_MASK_MARGIN) / scale / z / s[lane]
    start = torch.maximum(torch.maximum(t_in, behind), sphere.near / scale / s[lane])
    stop = torch.minimum(t_out, sphere.far / scale / s[lane])
    keep = (start <= stop).nonzero().squeeze(1)
    if keep.numel() == 0:
        return masks
    o_own = o_own[keep]
    o_own[:, 0] += torch.tensor(shifts, dtype=torch.float64)[lane[keep]]
    lanes = Lanes(objects, shifts)
    dtype, dev = lanes.bounds.dtype, lanes.device
    rays = [v.to(device=dev, dtype=dtype) for v in (o_own, d_own[keep], angle[keep], start[keep], stop[keep])]
    # Few rays, each starting near its surface: a distance grid would cost more than it saves.
    # Near and far are in each ray's span already (in its object's units).
    plain = dataclasses.replace(sphere, grid_resolution=0, near=0.0, far=math.inf)
    hit = trace(lanes, rays[0], rays[1], plain, None, *rays[2:]).hit.cpu().numpy()
    kept = keep.numpy()[hit]
    lane_hit, view_hit, rows_hit, cols_hit = lane.numpy()[kept], view[kept], rows[kept], cols[kept]
    for k in range(len(cameras)):  # a loop over views: every hit of the view at once
        at = view_hit == k
        whole = np.stack([masks[iid][k] for iid in ids_of])
        whole[lane_hit[at], rows_hit[at], cols_hit[at]] = True
        for g, iid in enumerate(ids_of):  # a loop over instances
            masks[iid][k] = whole[g]
    return masks


def box_window(camera: Any, corners: np.ndarray, near: float = 1e-3) -> tuple[int, int, int, int] | None:
    """The pixels ``(x0, y0, x1, y1)`` (end exclusive) that hold the projection of a box.

    Parameters
    ----------
    camera : Camera
    corners : (8, 3) float
        The box's corners, world metres.
    near : float
        A corner nearer the camera's plane than this (metres), or behind it: the whole image.

    Returns
    -------
    tuple of int, or None
        None when the box projects outside the image.
    """
    c2w = np.asarray(camera.camera_to_world, np.float64)
    local = (corners - c2w[:3, 3]) @ c2w[:3, :3]
    if (local[:, 2] <= near).any():
        return 0, 0, int(camera.width), int(camera.height)
    K = np.asarray(camera.K, np.float64)
    uv = local @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    # Pixel (u, v) is sampled at (u + 0.5, v + 0.5): a pixel of the window's border stays in.
    x0, y0 = np.floor(uv.min(axis=0) - 1.0).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0) + 1.0).astype(int)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, int(camera.width)), min(y1, int(camera.height))
    return (int(x0), int(y0), int(x1), int(y1)) if x1 > x0 and y1 > y0 else None
