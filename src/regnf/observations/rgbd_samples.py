"""Turn posed RGB-D frames into the training samples of a neural SDF.

Every valid depth pixel back-projects to a surface point with its colour, the ray it was
seen along, and (away from depth discontinuities) a normal from the depth image's local
tangent plane. Pixels with no depth become free rays (nothing lies along them, which carves
the silhouette) only where the capture says a zero depth is empty (the void around a library
object in regnf's ideal renders, :attr:`regnf.captures.model.Capture.zero_depth_is_empty`);
elsewhere (a sensor's missing return) they give no sample at all. Rays beside an occluding edge
(a depth step to a closer neighbour, or an empty pixel next to a pixel with depth) are kept
apart as well: they pass within about a pixel footprint of the occluder's outline.

Depth as a sensor writes it (a capture with a noise model,
:attr:`regnf.captures.model.Capture.depth_noise`) is trusted less than regnf's ideal renders:
mixed ("flying") pixels at depth discontinuities and surfaces seen beyond
:data:`MAX_INCIDENCE_DEG` are dropped as unknown (:func:`flying_pixels`), and each sample gets
its depth's sigma and a weight (:func:`frame_pixels`). A confidence map
(:attr:`regnf.captures.model.CaptureFrame.confidence_path`, ARKit's 0 / 1 / 2) makes its
low-confidence pixels unknown and halves the weight of its medium ones
(:data:`regnf.captures.depth_uncertainty.CONFIDENCE_WEIGHTS`). An ideal capture's samples are
exactly what they were before any of this.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np
import torch

from regnf.captures.depth_io import read_confidence
from regnf.captures.depth_uncertainty import CONFIDENCE_WEIGHTS, DepthNoiseModel
from regnf.captures.distortion import Distortion, pixels_to_rays
from regnf.captures.model import META_NAME, CaptureError
from regnf.core.cameras import ray_aabb
from regnf.core.errors import RegnfError
from regnf.observations.depth_normals import EDGE_STEP_FOOTPRINTS, depth_normals, window_normals


class CaptureLike(Protocol):
    """What the sample builder needs from a capture (``regnf.captures.model.Capture``)."""

    width: int
    height: int
    frames: Sequence
    zero_depth_is_empty: bool
    depth_noise: DepthNoiseModel | None
    scale: float

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
    weights: torch.Tensor | None = None
    """(m,) float32 weight of each point's depth in (0, 1]: all ones where the depth is exact (see :func:`frame_pixels`)."""
    sigma: torch.Tensor | None = None
    """(m,) float32 axial depth noise of each point, normalised units (0 where the depth is exact)."""
    frame: torch.Tensor | None = None
    """(m,) int32 index into the ``indices`` given to :func:`build_samples` of the frame each point came from."""
    free_frame: torch.Tensor | None = None
    """(k,) int32 frame (index into ``indices``) of each free ray."""
    edge_frame: torch.Tensor | None = None
    """(e,) int32 frame (index into ``indices``) of each edge ray."""
    ray_free_t: torch.Tensor | None = None
    """(m,) distance along each point's ray up to which it is free (before the margin); None:
    ``ray_t`` (exact depth; see :func:`free_depths` for a sensor's)."""


def camera_rays(K: np.ndarray, h: int, w: int, distortion: Distortion | None = None) -> np.ndarray:
    """(h, w, 3) camera-frame rays K^-1 [u + 0.5, v + 0.5, 1] through the pixel centres (z = 1).

    With a ``distortion`` the ray is ``(x, y, 1)``, ``(x, y)`` the undistorted normalised
    coordinates of the pixel centre (:func:`regnf.captures.distortion.pixels_to_rays`, computed
    once per camera; read-only); NaN where the lens model has no ray for the pixel.
    """
    if distortion is not None:
        return _distorted_rays(tuple(np.asarray(K, dtype=np.float64).ravel().tolist()), h, w, distortion)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)


@functools.lru_cache(maxsize=4)
def _distorted_rays(K: tuple[float, ...], h: int, w: int, distortion: Distortion) -> np.ndarray:
    """:func:`camera_rays` of a distorted camera; cached: every frame of a capture shares it."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = pixels_to_rays(np.stack([u, v], -1), np.reshape(K, (3, 3)), distortion)
    rays = np.concatenate([xy, np.ones_like(u)[..., None]], -1)
    rays.flags.writeable = False
    return rays


def backproject_frame(
    depth: np.ndarray, K: np.ndarray, camtoworld: np.ndarray, distortion: Distortion | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project a z-depth image through pixel centres.

    Depth is z along the optical axis: the point is the pixel's ray ``(x, y, 1)``
    (:func:`camera_rays`, undistorted where the frame has a ``distortion``) times the depth.

    Parameters
    ----------
    depth : (h, w) float
        z-depth, 0 (or non-finite) where nothing was hit.
    K : (3, 3) float
    camtoworld : (4, 4) float, OpenCV convention.
    distortion : Distortion, optional
        The frame's lens distortion; None: an ideal pinhole.

    Returns
    -------
    points : (h, w, 3) float   world points (undefined where invalid)
    dirs : (h, w, 3) float     unit ray directions in world (NaN for a pixel without a ray)
    valid : (h, w) bool        depth > 0 and finite, and the pixel has a ray
    """
    cam = camera_rays(K, *depth.shape, distortion)
    R, t = camtoworld[:3, :3], camtoworld[:3, 3]
    d_world = cam @ R.T
    valid = np.isfinite(depth) & (depth > 0)
    if distortion is not None:
        valid &= np.isfinite(cam[..., 0])
    z = np.where(valid, depth, 0.0)
    points = d_world * z[..., None] + t
    dirs = d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)
    return points, dirs, valid


def edge_depths(
    depth: np.ndarray, valid: np.ndarray, K: np.ndarray, zeros_empty: bool | np.ndarray = True
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
    zeros_empty : bool or (h, w) bool
        Pixels without depth saw nothing (True) or are unknown (False); per pixel where some
        pixels were dropped (:attr:`FramePixels.empty`).

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
    depth: np.ndarray, valid: np.ndarray, K: np.ndarray, zeros_empty: bool | np.ndarray = True
) -> np.ndarray:
    """(h, w) bool: pixels with depth that are an occluder beside an occluding edge.

    The other side of :func:`edge_depths`: a pixel with depth one of whose 4 neighbours is empty
    (``zeros_empty`` and no depth) or lies farther by more than :data:`EDGE_STEP_FOOTPRINTS`
    pixel footprints. Its point lies on the silhouette the neighbour's ray passes, seen at a
    grazing angle: few pixels see such a surface, and their points hold the outline where the
    edge samples push it. A neighbour of unknown depth says nothing, like one beyond the image.
    ``zeros_empty`` is a bool or (h, w) bool, as in :func:`edge_depths`.
    """
    z = np.where(valid, depth, np.where(zeros_empty, np.inf, -np.inf))
    pad = np.pad(z, 1, constant_values=-np.inf)  # beyond the image: nothing behind
    farthest = np.stack([pad[1:-1, 2:], pad[1:-1, :-2], pad[2:, 1:-1], pad[:-2, 1:-1]]).max(0)
    step = EDGE_STEP_FOOTPRINTS * depth / K[0, 0]
    return valid & (farthest > depth + step)


MAX_INCIDENCE_DEG = 80.0
"""Largest angle between a ray and the surface normal at which a sensor's depth is used, degrees.

Beyond it the depth is dropped as unknown (as the synthetic sensor gives no return there,
``max_incidence_deg``); the same angle bounds the steps of a mixed pixel
(:func:`flying_pixels`). docs/decisions/depth-weights.md says why 80."""


def flying_pixels(depth: np.ndarray, valid: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(h, w) bool: mixed ("flying") pixels, whose depth belongs to neither side of a discontinuity.

    A sensor averages the two surfaces a pixel straddles at a depth step, and reports a point
    floating between them. Such a pixel's depth lies between those of two opposite neighbours
    (left and right, or above and below), farther than ``tan(MAX_INCIDENCE_DEG)`` pixel
    footprints (z / f) from each: no surface seen at :data:`MAX_INCIDENCE_DEG` or less steps
    that far per pixel, so no surface the samples keep explains it. The pixels on either side
    of the step, each next to a neighbour on its own surface, stay.

    Parameters
    ----------
    depth : (h, w) float
        z-depth.
    valid : (h, w) bool
        Pixels with depth; a neighbour without depth is never one of the two.
    K : (3, 3) float

    Returns
    -------
    (h, w) bool
    """
    z = np.where(valid, depth, np.nan)
    pad = np.pad(z, 1, constant_values=np.nan)
    gap = np.tan(np.radians(MAX_INCIDENCE_DEG)) * z / K[0, 0]
    mixed = np.zeros(depth.shape, dtype=bool)
    for a, b in ((pad[1:-1, :-2], pad[1:-1, 2:]), (pad[:-2, 1:-1], pad[2:, 1:-1])):  # the two axes
        # NaN (a neighbour without depth) fails both comparisons.
        mixed |= (z - np.minimum(a, b) > gap) & (np.maximum(a, b) - z > gap)
    return valid & mixed


def incidence(normals: np.ndarray, ok: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(h, w) angle between each pixel's ray and its depth normal, radians; 0 where the normal is not trusted."""
    cos = np.abs((normals * dirs).sum(-1))
    return np.where(ok, np.arccos(np.clip(cos, 0.0, 1.0)), 0.0)


def frame_confidence(capture: CaptureLike, i: int) -> np.ndarray | None:
    """(h, w) uint8 depth confidence of frame ``i`` (0, 1, 2); None where the frame has none.

    Raises
    ------
    CaptureError
        See :func:`regnf.captures.depth_io.read_confidence`; the message names the file and the frame.
    """
    path = getattr(capture.frames[i], "confidence_path", None)
    if path is None:
        return None
    try:
        return read_confidence(path, capture.height, capture.width)
    except ValueError as exc:
        raise CaptureError(f"{path}: frame {i}: {exc}") from exc


LATERAL_READ_SIGMAS = 2.0
"""How many sigmas of lateral noise away from its pixel's centre a depth may have been read."""


def free_window_radius(lateral_px: float) -> int:
    """Radius of the window whose nearest depth bounds a sensor pixel's free space, pixels.

    A depth read up to :data:`LATERAL_READ_SIGMAS` x ``lateral_px`` from the pixel's centre
    (``lateral_px``: :attr:`~regnf.captures.depth_uncertainty.DepthNoiseModel.lateral_px`)
    reaches beyond the pixel's own half-pixel as far as ``ceil(2 sigma - 1/2)`` neighbours: 1 for
    ICL-NUIM's half a pixel, 0 for a read that stays within the pixel (docs/decisions/depth-weights.md).
    """
    return max(0, math.ceil(LATERAL_READ_SIGMAS * lateral_px - 0.5))


def free_depths(depth: np.ndarray, valid: np.ndarray, radius: int) -> np.ndarray:
    """(h, w) the nearest depth in each pixel's window: how far a sensor pixel's ray is free.

    A sensor reads each pixel's depth at a position jittered by its lateral noise: beside an
    object's outline a ray that passes through the object may report the wall behind it, and
    free space along it would carve the object. Its neighbours see the object, so the ray is
    taken as free only up to the nearest depth of its ``(2 radius + 1)^2`` window
    (:func:`free_window_radius`). On a slanted surface that ends free space up to one pixel's
    step early (a few footprints at grazing angles): free space is given up near the surface,
    never invented. The same bound ends the occluding-edge samples of a pixel beside an
    outline, so a radius of 1 or more leaves them none there.

    Parameters
    ----------
    depth : (h, w) float
        z-depth.
    valid : (h, w) bool
        Pixels whose depth is used; the others are left out of every window.
    radius : int

    Returns
    -------
    (h, w) float64
        ``inf`` where no pixel of the window has depth.
    """
    z = np.where(valid, depth, np.inf).astype(np.float64)
    h, w = z.shape
    pad = np.pad(z, radius, constant_values=np.inf)
    size = 2 * radius + 1
    return np.min([pad[i : i + h, j : j + w] for i in range(size) for j in range(size)], axis=0)


class FramePixels(NamedTuple):
    """One frame's pixels as the samples use them, all (h, w) at full resolution."""

    depth: np.ndarray
    """float64 z-depth, normalised units (0 where a sensor's pixel was dropped)."""
    points: np.ndarray
    """(h, w, 3) float64 back-projected points (undefined where not ``valid``)."""
    dirs: np.ndarray
    """(h, w, 3) float64 unit ray directions."""
    valid: np.ndarray
    """bool: the pixel's depth is used."""
    normals: np.ndarray
    """(h, w, 3) float64 depth normals facing the camera (0 where not ``ok``)."""
    ok: np.ndarray
    """bool: the normal is trusted (see :func:`depth_normals`)."""
    empty: bool | np.ndarray
    """Where a pixel without depth saw nothing: the capture's rule, or (h, w) bool where some were dropped."""
    sigma: np.ndarray | None
    """float64 axial depth noise, normalised units; None where the depth is exact."""
    weight: np.ndarray | None
    """float64 weight of the pixel's depth in (0, 1]; None where the depth is exact."""
    free_depth: np.ndarray | None
    """float64 z-depth up to which the pixel's ray is free (:func:`free_depths`); None: ``depth``."""


def frame_pixels(
    capture: CaptureLike, i: int, zeros_empty: bool, noise: DepthNoiseModel | None
) -> FramePixels:
    """Back-project frame ``i`` and decide which of its depth pixels to use and how much.

    Where the depth is exact (``noise`` None, no confidence map) this is the depth as read.
    Otherwise pixels are dropped as unknown (no sample, no free ray, no edge; a neighbour of
    unknown depth) where the confidence is 0 and, with a noise model, at flying pixels
    (:func:`flying_pixels`) and where the surface is seen beyond :data:`MAX_INCIDENCE_DEG`.
    With a noise model each pixel gets ``sigma`` from its z-depth in metres (``capture.scale``)
    and its incidence (0 where the normal is not trusted), and the weight
    :meth:`~regnf.captures.depth_uncertainty.DepthNoiseModel.weight` of it times the
    confidence's factor (:data:`~regnf.captures.depth_uncertainty.CONFIDENCE_WEIGHTS`).

    Parameters
    ----------
    capture : CaptureLike
    i : int
        The frame.
    zeros_empty : bool
        The capture's :attr:`~CaptureLike.zero_depth_is_empty`.
    noise : DepthNoiseModel or None
        The capture's :attr:`~CaptureLike.depth_noise`.

    Raises
    ------
    CaptureError
        A frame without depth, an invalid depth or confidence file (naming the file and the frame).
    """
    frame = capture.frames[i]
    depth = capture.depth(i)
    if depth is None:
        raise CaptureError(
            f"{capture_where(capture)}: frame {i} of the capture has no depth; RGB-D training needs depth"
        )
    K = np.asarray(frame.intrinsics, dtype=np.float64)
    c2w = np.asarray(frame.camtoworld, dtype=np.float64)
    depth = depth.astype(np.float64)
    p, d, valid = backproject_frame(depth, K, c2w, frame.distortion)
    n, ok = depth_normals(p, depth, valid, K, d)
    confidence = frame_confidence(capture, i)
    if noise is None and confidence is None:
        return FramePixels(depth, p, d, valid, n, ok, zeros_empty, None, None, None)
    drop = np.zeros_like(valid)
    if confidence is not None:
        drop |= confidence == 0
    if noise is not None:
        drop |= flying_pixels(depth, valid, K)
        # Central differences of noisy depth are mostly noise: windows (depth_normals.py).
        sigma0 = noise.sigma_normal(np.maximum(depth, 1e-12) * capture.scale) / capture.scale
        n_w, ok_w = window_normals(p, depth, valid & ~drop, K, d, sigma0)
        # The incidence from the window's normal, else the central difference's (as grazing
        # surfaces step too far per pixel for a whole window).
        theta = np.where(ok_w, incidence(n_w, ok_w, d), incidence(n, ok, d))
        n, ok = n_w, ok_w
        drop |= theta > np.radians(MAX_INCIDENCE_DEG)
    drop &= valid
    valid = valid & ~drop
    # depth_normals' neighbour rule on the new mask: a normal needs its 4 neighbours' depth.
    inner = np.zeros_like(ok)
    inner[1:-1, 1:-1] = valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    ok = ok & valid & inner
    n = np.where(ok[..., None], n, 0.0)
    depth = np.where(valid, depth, 0.0)
    # A dropped pixel is unknown, never a ray that hit nothing.
    empty = zeros_empty & ~drop
    if noise is None:
        return FramePixels(depth, p, d, valid, n, ok, empty, None, None, None)
    sigma_m = noise.sigma(depth * capture.scale, np.where(valid, theta, 0.0))
    factor = 1.0 if confidence is None else np.asarray(CONFIDENCE_WEIGHTS)[confidence]
    weight = noise.weight(sigma_m) * factor
    return FramePixels(depth, p, d, valid, n, ok, empty, sigma_m / capture.scale, weight,
                       free_depths(depth, valid, free_window_radius(noise.lateral_px)))


def measured_depth(capture: CaptureLike, i: int, free: bool = False) -> np.ndarray:
    """(h, w) z-depth of frame ``i`` as the samples use it, for tests of what a view saw.

    The depth as read where it is exact and the frame has no confidence map. Otherwise the
    pixels :func:`frame_pixels` drops are NaN: unknown even where zeros are empty, so they see
    nothing free and observe nothing. ``free``: each pixel's free depth instead of its depth
    (:func:`free_depths`; the same where the depth is exact), for tests of what a view saw free.
    """
    noise = capture.depth_noise
    if noise is None and getattr(capture.frames[i], "confidence_path", None) is None:
        return capture.depth(i)
    px = frame_pixels(capture, i, bool(capture.zero_depth_is_empty), noise)
    depth = px.free_depth if free and px.free_depth is not None else px.depth
    return np.where(px.valid, depth, np.where(px.empty, 0.0, np.nan))


def capture_where(capture: CaptureLike) -> str:
    """The capture's metadata file for messages (``capture`` for one without a root)."""
    root = getattr(capture, "root", None)
    return str(Path(root) / getattr(capture, "meta_name", META_NAME)) if root is not None else "capture"


def build_samples(capture: CaptureLike, indices: Sequence[int], pixel_stride: int = 1) -> RGBDSamples:
    """Gather the samples of frames ``indices`` of ``capture`` (one pass per frame).

    Pixels without depth become free rays and edge rays only where the capture's zeros are
    empty (:attr:`CaptureLike.zero_depth_is_empty`); where they are unknown they give nothing.
    Which depth pixels are used, and their weights, follow :func:`frame_pixels`.

    Parameters
    ----------
    capture : CaptureLike
    indices : sequence of int
        The frames; ``RGBDSamples.frame`` indexes this sequence.
    pixel_stride : int
        Sample every ``pixel_stride``-th pixel in u and v, from pixel (0, 0). Normals, edges and
        outlines are decided at full resolution first, so a kept pixel's samples are exactly
        those it gives at stride 1.

    Raises
    ------
    CaptureError
        A frame without depth, or the capture's own error for an invalid image or depth
        (:meth:`regnf.captures.model.Capture.depth` names the file and the frame).
    ValueError
        ``pixel_stride`` below 1.
    """
    if isinstance(pixel_stride, bool) or not isinstance(pixel_stride, (int, np.integer)) or pixel_stride < 1:
        raise RegnfError(f"pixel_stride must be an integer >= 1, got {pixel_stride!r}")
    pts, cols, nrm, nok, org, tt, forg, fdir = [], [], [], [], [], [], [], []
    eorg, edir, et, elim, outl = [], [], [], [], []
    wts, sig, frm, ffrm, efrm, ftt = [], [], [], [], [], []
    zeros_empty = bool(capture.zero_depth_is_empty)
    noise = capture.depth_noise
    for j, i in enumerate(indices):
        frame = capture.frames[i]
        px = frame_pixels(capture, i, zeros_empty, noise)
        rgb = capture.rgb(i)
        K = np.asarray(frame.intrinsics, dtype=np.float64)
        c2w = np.asarray(frame.camtoworld, dtype=np.float64)
        depth, p, d, valid, n, ok = px.depth, px.points, px.dirs, px.valid, px.normals, px.ok
        # A ray of unknown depth may have hit anything: it is no free ray.
        free = ~valid & px.empty
        z_edge = edge_depths(depth, valid, K, px.empty)
        outline = outline_pixels(depth, valid, K, px.empty)
        # z-depth to distance along the unit ray, as backproject_frame measures it.
        ray_len = np.linalg.norm(camera_rays(K, *depth.shape, frame.distortion) @ c2w[:3, :3].T, axis=-1)
        weight, sigma, free_depth = px.weight, px.sigma, px.free_depth
        if pixel_stride > 1:
            sub = np.s_[::pixel_stride, ::pixel_stride]
            depth, p, d, valid, n, ok, rgb, free, z_edge, outline, ray_len = (
                a[sub] for a in (depth, p, d, valid, n, ok, rgb, free, z_edge, outline, ray_len)
            )
            weight, sigma, free_depth = (None if a is None else a[sub] for a in (weight, sigma, free_depth))
        at_edge = z_edge > 0
        origin = c2w[:3, 3]
        count = int(valid.sum())
        pts.append(p[valid].astype(np.float32))
        cols.append(rgb[valid])
        nrm.append(n[valid].astype(np.float32))
        nok.append(ok[valid])
        org.append(np.broadcast_to(origin.astype(np.float32), (count, 3)))
        tt.append(np.linalg.norm(p[valid] - origin, axis=-1).astype(np.float32))
        forg.append(np.broadcast_to(origin.astype(np.float32), (int(free.sum()), 3)))
        fdir.append(d[free].astype(np.float32))
        own = np.where(valid, (depth if free_depth is None else free_depth) * ray_len, np.inf)
        if free_depth is not None:
            ftt.append((free_depth * ray_len)[valid].astype(np.float32))
        eorg.append(np.broadcast_to(origin.astype(np.float32), (int(at_edge.sum()), 3)))
        edir.append(d[at_edge].astype(np.float32))
        et.append((z_edge * ray_len)[at_edge].astype(np.float32))
        elim.append(own[at_edge].astype(np.float32))
        outl.append(outline[valid])
        wts.append(np.ones(count, np.float32) if weight is None else weight[valid].astype(np.float32))
        sig.append(np.zeros(count, np.float32) if sigma is None else sigma[valid].astype(np.float32))
        frm.append(np.full(count, j, dtype=np.int32))
        ffrm.append(np.full(int(free.sum()), j, dtype=np.int32))
        efrm.append(np.full(int(at_edge.sum()), j, dtype=np.int32))

    def cat(a: list, width: int | None = 3) -> torch.Tensor:
        # Each frame's part turned to float32 on its own (the same rounding as after joining
        # them): the peak holds the parts and the result in float32, never a float64 copy.
        parts = [np.asarray(x, dtype=np.float32) for x in a]
        del a[:]
        arr = np.concatenate(parts, 0) if parts else np.zeros((0, width) if width else (0,), np.float32)
        del parts
        return torch.from_numpy(np.ascontiguousarray(arr))

    def cat_int(a: list) -> torch.Tensor:
        return torch.from_numpy(np.concatenate(a, 0) if a else np.zeros(0, dtype=np.int32))

    return RGBDSamples(
        points=cat(pts), colors=cat(cols), normals=cat(nrm),
        normal_ok=torch.from_numpy(np.concatenate(nok, 0)) if nok else torch.zeros(0, dtype=torch.bool),
        origins=cat(org), ray_t=cat(tt, None), free_origins=cat(forg), free_dirs=cat(fdir),
        edge_origins=cat(eorg), edge_dirs=cat(edir), edge_t=cat(et, None), edge_limit=cat(elim, None),
        outline=torch.from_numpy(np.concatenate(outl, 0)) if outl else torch.zeros(0, dtype=torch.bool),
        weights=cat(wts, None), sigma=cat(sig, None), frame=cat_int(frm), free_frame=cat_int(ffrm),
        edge_frame=cat_int(efrm), ray_free_t=cat(ftt, None) if noise is not None else None,
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
