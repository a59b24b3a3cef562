"""Whole silhouettes of a variant's objects, hidden parts included: each object traced alone.

A view's own images decide most pixels: where the composite shows the instance, the object
alone is hit too (the composite's first hit is its first); where the view shows no surface,
nothing is hit; where it shows a surface beyond the object's box, the ray crossed the box
and met nothing. Only the other pixels whose ray crosses the object's box in front of the
surface the view shows are traced, each from just before that surface (the object lies
behind it) to where it leaves the box.

Every object's rays go in one trace: the objects stand side by side in a field of lanes
(:class:`Lanes`), each ray moved into its object's lane and stopped where it leaves the
object's box, so that it meets no other object. One trace pays the tracer's per-step cost
once for all the objects, not once per object.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from regnf.neural_fields.field import Field, FieldInfo, FieldSample

FULL_MASK_MARGIN = 0.005
"""How far before the surface a view shows a pixel's trace of a hidden object starts, metres
(depth images hold whole millimetres)."""


class Lanes(Field):
    """Fields side by side along x, lane ``k`` moved by ``shifts[k]``: a point is evaluated by
    the field of the lane it lies in.

    Parameters
    ----------
    fields : sequence of Field
        One frame (the same ``to_world``) and device.
    shifts : (k,) float
        Each field's move along x, field units, increasing; lanes must not overlap.
    """

    def __init__(self, fields: Sequence[Field], shifts: Sequence[float]) -> None:
        lo = torch.stack([f.bounds[0].double() + torch.tensor([s, 0.0, 0.0], dtype=torch.float64, device=f.device)
                          for f, s in zip(fields, shifts, strict=True)])
        hi = torch.stack([f.bounds[1].double() + torch.tensor([s, 0.0, 0.0], dtype=torch.float64, device=f.device)
                          for f, s in zip(fields, shifts, strict=True)])
        if bool((lo[1:, 0] <= hi[:-1, 0]).any()):
            raise ValueError("lanes overlap: each shift must clear the lane before it")
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
    from regnf.neural_fields.analytic import Transformed
    from regnf.neural_fields.sphere_tracer import trace

    views = [(read_instance_png(folder / view_files(k).instance), read_depth_png(folder / view_files(k).depth))
             for k in range(len(cameras))]
    ids_of = [int(i) for i in field.instance_ids]
    masks = {iid: [ids == iid for ids, _ in views] for iid in ids_of}
    alone = [Transformed(p.mapped.child, p.mapped.matrix, to_world=field.to_world) for p in field.placements]
    if not alone:
        return masks
    to_world = field.to_world.detach().cpu().double()
    world_to_field = torch.linalg.inv(to_world)
    scale = float(alone[0].world_scale)  # metres per field unit, the same for every lane
    boxes = [a.bounds.detach().cpu().double() for a in alone]
    widths = torch.stack([hi - lo for lo, hi in boxes])
    gap = float(widths.norm(dim=1).max()) + 2 * sphere.bounds_pad
    shifts, edge = [], 0.0
    for lo, hi in boxes:  # a loop over instances: each lane starts a gap after the last one
        shifts.append(0.0 if not shifts else edge + gap - float(lo[0]))
        edge = float(hi[0]) + shifts[-1]
    near, far = sphere.near / scale, sphere.far / scale
    parts: dict[str, list[torch.Tensor]] = {"o": [], "d": [], "start": [], "stop": [], "angle": []}
    where = []
    for lane, (iid, (lo, hi)) in enumerate(zip(ids_of, boxes, strict=True)):  # a loop over instances
        lo, hi = lo - sphere.bounds_pad, hi + sphere.bounds_pad
        corners = torch.stack(torch.meshgrid(*(torch.stack((lo[i], hi[i])) for i in range(3)), indexing="ij"), dim=-1).reshape(-1, 3)
        corners = (corners @ to_world[:3, :3].T + to_world[:3, 3]).numpy()
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
            if rows.size == 0:
                continue
            rows, cols = rows + y0, cols + x0
            C = world_to_field @ torch.as_tensor(cam.camera_to_world, dtype=torch.float64)
            o, d, z = rays_through(torch.as_tensor(cam.K, dtype=torch.float64), C,
                                   torch.from_numpy(cols + 0.5), torch.from_numpy(rows + 0.5))
            t_in, t_out = ray_aabb(o, d, lo, hi)
            # Metres of z-depth to field units along the ray, less a margin for the depth's rounding.
            behind = (torch.from_numpy(depth[rows, cols].astype(np.float64)) - FULL_MASK_MARGIN) / scale / z
            start = torch.maximum(torch.maximum(t_in, behind), torch.full_like(t_in, near))
            stop = t_out.clamp(max=far)
            keep = (start <= stop).nonzero().squeeze(1)
            if keep.numel() == 0:
                continue
            o = o[keep].clone()
            o[:, 0] += shifts[lane]
            parts["o"].append(o)
            parts["d"].append(d[keep])
            parts["start"].append(start[keep])
            parts["stop"].append(stop[keep])
            parts["angle"].append(torch.full((keep.numel(),), 1.0 / float(min(cam.K[0, 0], cam.K[1, 1])),
                                             dtype=torch.float64))
            where.append((iid, k, rows[keep.numpy()], cols[keep.numpy()]))
    if not where:
        return masks
    lanes = Lanes(alone, shifts)
    dtype, dev = lanes.bounds.dtype, lanes.device
    cat = {n: torch.cat(v).to(device=dev, dtype=dtype) for n, v in parts.items()}
    # Few rays, each starting near its surface: a distance grid would cost more than it saves.
    plain = dataclasses.replace(sphere, grid_resolution=0)
    hit = trace(lanes, cat["o"], cat["d"], plain, None, cat["angle"], cat["start"], cat["stop"]).hit.cpu().numpy()
    first = 0
    for iid, k, rows, cols in where:  # a loop over instances and views
        masks[iid][k][rows, cols] |= hit[first:first + len(rows)]
        first += len(rows)
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
