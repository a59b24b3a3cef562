"""Turn posed RGB-D frames into the training samples of a neural SDF.

Every valid depth pixel back-projects to a surface point with its colour, the ray it was
seen along, and (away from depth discontinuities) a normal from the depth image's local
tangent plane. Pixels with no depth become free rays (nothing lies along them, which carves
the silhouette) only where the capture says a zero depth is empty (the void around a library
object in regnf's ideal renders, :attr:`regnf.captures.model.Capture.zero_depth_is_empty`);
elsewhere (a sensor's missing return) they give no sample at all. Rays beside an occluding edge
(a depth step to a closer neighbour, or an empty pixel next to a pixel with depth) are kept
apart as well: they pass within about a pixel footprint of the occluder's outline.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np
import torch

from regnf.captures.model import META_NAME, CaptureError
from regnf.core.cameras import ray_aabb


class CaptureLike(Protocol):
    """What the sample builder needs from a capture (``regnf.captures.model.Capture``)."""

    width: int
    height: int
    frames: Sequence
    zero_depth_is_empty: bool

    def rgb(self, i: int) -> np.ndarray: ...
    def depth(self, i: int) -> np.ndarray | None: ...


class RGBDSamples(NamedTuple):
    """Per-pixel training samples, all in the field (normalised) frame."""

    points: torch.Tensor
    """(m, 3) back-projected surface points."""
    colors: torch.Tensor
    """(m, 3) RGB in [0, 1]."""
    normals: torch.Tensor
    """(m, 3) unit normals facing the camera (zero where unreliable)."""
    normal_ok: torch.Tensor
    """(m,) bool: normal (and colour) away from depth discontinuities."""
    origins: torch.Tensor
    """(m, 3) camera centres of the rays that saw the points."""
    ray_t: torch.Tensor
    """(m,) distance from the origin to the point along the unit ray."""
    free_origins: torch.Tensor
    """(k, 3) origins of rays that hit nothing (none where zero depth is unknown)."""
    free_dirs: torch.Tensor
    """(k, 3) unit directions of rays that hit nothing."""
    edge_origins: torch.Tensor
    """(e, 3) origins of the rays that pass an occluding edge (see :func:`edge_depths`)."""
    edge_dirs: torch.Tensor
    """(e, 3) unit directions of those rays."""
    edge_t: torch.Tensor
    """(e,) distance along the ray at which it passes the edge (the occluder's depth)."""
    edge_limit: torch.Tensor
    """(e,) distance along the ray to its own hit; ``inf`` for a ray that hit nothing."""
    outline: torch.Tensor
    """(m,) bool: the point is on an occluder's outline (see :func:`outline_pixels`)."""


def camera_rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(h, w, 3) camera-frame rays K^-1 [u + 0.5, v + 0.5, 1] through the pixel centres (z = 1)."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)


def backproject_frame(
    depth: np.ndarray, K: np.ndarray, camtoworld: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project a z-depth image through pixel centres.

    Parameters
    ----------
    depth : (h, w) float
        z-depth, 0 (or non-finite) where nothing was hit.
    K : (3, 3) float
    camtoworld : (4, 4) float, OpenCV convention.

    Returns
    -------
    points : (h, w, 3) float   world points (undefined where invalid)
    dirs : (h, w, 3) float     unit ray directions in world
    valid : (h, w) bool
    """
    cam = camera_rays(K, *depth.shape)
    R, t = camtoworld[:3, :3], camtoworld[:3, 3]
    d_world = cam @ R.T
    valid = np.isfinite(depth) & (depth > 0)
    z = np.where(valid, depth, 0.0)
    points = d_world * z[..., None] + t
    dirs = d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)
    return points, dirs, valid


EDGE_STEP_FOOTPRINTS = 8.0
"""A depth step between neighbouring pixels larger than this many pixel footprints (z / f) is
a discontinuity (an occluding edge), not a slanted surface."""


def edge_depths(
    depth: np.ndarray, valid: np.ndarray, K: np.ndarray, zeros_empty: bool = True
) -> np.ndarray:
    """(h, w) float: for each pixel beside an occluding edge, the z-depth of the occluder; else 0.

    A pixel is beside an occluding edge when one of its 4 neighbours has depth and lies closer by
    more than :data:`EDGE_STEP_FOOTPRINTS` pixel footprints (every neighbour with depth counts
    for an empty pixel; a pixel of unknown depth is beside no edge). Its ray then passes within about a pixel footprint of the
    occluder's silhouette at the occluder's depth, through space that is empty (it is in front
    of the pixel's own surface): the samples that pin a silhouette where it was seen.

    Parameters
    ----------
    depth : (h, w) float
        z-depth, 0 where nothing was hit.
    valid : (h, w) bool
    K : (3, 3) float
    zeros_empty : bool
        Pixels without depth saw nothing (True) or are unknown (False).

    Returns
    -------
    (h, w) float
        The smallest closer neighbour depth, 0 where the pixel is beside no edge.
    """
    z = np.where(valid, depth, np.inf)
    pad = np.pad(z, 1, constant_values=np.inf)
    neigh = np.stack([pad[1:-1, 2:], pad[1:-1, :-2], pad[2:, 1:-1], pad[:-2, 1:-1]])
    nearest = neigh.min(0)
    step = EDGE_STEP_FOOTPRINTS * np.where(valid, depth, nearest) / K[0, 0]
    # An empty pixel is beside an edge as soon as it has a neighbour with depth.
    edge = np.isfinite(nearest) & ((~valid & zeros_empty) | (nearest < depth - step))
    return np.where(edge, nearest, 0.0)


def outline_pixels(
    depth: np.ndarray, valid: np.ndarray, K: np.ndarray, zeros_empty: bool = True
) -> np.ndarray:
    """(h, w) bool: pixels with depth that are an occluder beside an occluding edge.

    The other side of :func:`edge_depths`: a pixel with depth one of whose 4 neighbours is empty
    (``zeros_empty`` and no depth) or lies farther by more than :data:`EDGE_STEP_FOOTPRINTS`
    pixel footprints. Its point lies on the silhouette the neighbour's ray passes, seen at a
    grazing angle: few pixels see such a surface, and their points hold the outline where the
    edge samples push it. A neighbour of unknown depth says nothing, like one beyond the image.
    """
    z = np.where(valid, depth, np.inf if zeros_empty else -np.inf)
    pad = np.pad(z, 1, constant_values=-np.inf)  # beyond the image: nothing behind
    farthest = np.stack([pad[1:-1, 2:], pad[1:-1, :-2], pad[2:, 1:-1], pad[:-2, 1:-1]]).max(0)
    step = EDGE_STEP_FOOTPRINTS * depth / K[0, 0]
    return valid & (farthest > depth + step)


def depth_normals(
    points: np.ndarray, depth: np.ndarray, valid: np.ndarray, K: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (h, w, 3) from central differences of back-projected points, and a mask.

    A pixel's normal is trusted only when its 4 neighbours have depth and no one-sided depth
    step exceeds :data:`EDGE_STEP_FOOTPRINTS` pixel footprints (a discontinuity, not a slanted
    surface).
    """
    h, w = depth.shape
    normals = np.zeros_like(points)
    ok = np.zeros((h, w), dtype=bool)
    c = (slice(1, -1), slice(1, -1))
    du = points[1:-1, 2:] - points[1:-1, :-2]
    dv = points[2:, 1:-1] - points[:-2, 1:-1]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = n / np.maximum(norm, 1e-12)
    # Face the camera: the normal and the viewing ray point against each other.
    flip = (n * dirs[c]).sum(-1, keepdims=True) > 0
    n = np.where(flip, -n, n)
    z = depth
    footprint = z[c] / K[0, 0]
    steps = np.stack(
        [
            np.abs(z[1:-1, 2:] - z[c]), np.abs(z[c] - z[1:-1, :-2]),
            np.abs(z[2:, 1:-1] - z[c]), np.abs(z[c] - z[:-2, 1:-1]),
        ],
        -1,
    ).max(-1)
    neigh = valid[c] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    good = neigh & (steps < EDGE_STEP_FOOTPRINTS * footprint) & (norm[..., 0] > 0)
    normals[c] = np.where(good[..., None], n, 0.0)
    ok[c] = good
    return normals, ok


def capture_where(capture: CaptureLike) -> str:
    """The capture's metadata file for messages (``capture`` for one without a root)."""
    root = getattr(capture, "root", None)
    return str(Path(root) / getattr(capture, "meta_name", META_NAME)) if root is not None else "capture"


def build_samples(capture: CaptureLike, indices: Sequence[int]) -> RGBDSamples:
    """Gather the samples of frames ``indices`` of ``capture`` (one pass per frame).

    Pixels without depth become free rays and edge rays only where the capture's zeros are
    empty (:attr:`CaptureLike.zero_depth_is_empty`); where they are unknown they give nothing.

    Raises
    ------
    CaptureError
        A frame without depth, or the capture's own error for an invalid image or depth
        (:meth:`regnf.captures.model.Capture.depth` names the file and the frame).
    """
    pts, cols, nrm, nok, org, tt, forg, fdir = [], [], [], [], [], [], [], []
    eorg, edir, et, elim, outl = [], [], [], [], []
    zeros_empty = bool(capture.zero_depth_is_empty)
    for i in indices:
        frame = capture.frames[i]
        depth = capture.depth(i)
        if depth is None:
            raise CaptureError(
                f"{capture_where(capture)}: frame {i} of the capture has no depth; RGB-D training needs depth"
            )
        rgb = capture.rgb(i)
        K = np.asarray(frame.intrinsics, dtype=np.float64)
        c2w = np.asarray(frame.camtoworld, dtype=np.float64)
        depth = depth.astype(np.float64)
        p, d, valid = backproject_frame(depth, K, c2w)
        n, ok = depth_normals(p, depth, valid, K, d)
        origin = c2w[:3, 3]
        pts.append(p[valid])
        cols.append(rgb[valid])
        nrm.append(n[valid])
        nok.append(ok[valid])
        org.append(np.broadcast_to(origin, (int(valid.sum()), 3)))
        tt.append(np.linalg.norm(p[valid] - origin, axis=-1))
        # A ray of unknown depth may have hit anything: it is no free ray.
        free = ~valid if zeros_empty else np.zeros_like(valid)
        forg.append(np.broadcast_to(origin, (int(free.sum()), 3)))
        fdir.append(d[free])
        z_edge = edge_depths(depth, valid, K, zeros_empty)
        at_edge = z_edge > 0
        # z-depth to distance along the unit ray, as backproject_frame measures it.
        ray_len = np.linalg.norm(camera_rays(K, *depth.shape) @ c2w[:3, :3].T, axis=-1)
        own = np.where(valid, depth * ray_len, np.inf)
        eorg.append(np.broadcast_to(origin, (int(at_edge.sum()), 3)))
        edir.append(d[at_edge])
        et.append((z_edge * ray_len)[at_edge])
        elim.append(own[at_edge])
        outl.append(outline_pixels(depth, valid, K, zeros_empty)[valid])

    def cat(a: list, width: int | None = 3) -> torch.Tensor:
        arr = np.concatenate(a, 0) if a else np.zeros((0, width) if width else (0,))
        return torch.from_numpy(np.ascontiguousarray(arr)).float()

    return RGBDSamples(
        points=cat(pts), colors=cat(cols), normals=cat(nrm),
        normal_ok=torch.from_numpy(np.concatenate(nok, 0)) if nok else torch.zeros(0, dtype=torch.bool),
        origins=cat(org), ray_t=cat(tt, None), free_origins=cat(forg), free_dirs=cat(fdir),
        edge_origins=cat(eorg), edge_dirs=cat(edir), edge_t=cat(et, None), edge_limit=cat(elim, None),
        outline=torch.from_numpy(np.concatenate(outl, 0)) if outl else torch.zeros(0, dtype=torch.bool),
    )


def ray_box_interval(
    origins: torch.Tensor, dirs: torch.Tensor, bounds: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances (n,) of rays through an AABB ``bounds`` (2, 3).

    The slab test (:func:`regnf.core.cameras.ray_aabb`) with the entry clamped at 0. A ray that
    misses the box gets the empty interval (0, -1), so that points sampled on it stay finite
    (training masks them out).
    """
    t_in, t_out = ray_aabb(origins, dirs, bounds[0], bounds[1])
    t_in = t_in.clamp_min(0.0)
    miss = ~(t_out >= t_in)
    return torch.where(miss, 0.0, t_in), torch.where(miss, -1.0, t_out)
