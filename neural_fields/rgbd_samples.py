"""Turn posed RGB-D frames into the training samples of a neural SDF.

Every valid depth pixel back-projects to a surface point with its colour, the ray it was
seen along, and (away from depth discontinuities) a normal from the depth image's local
tangent plane. Pixels with no depth (the void around a library object) become free rays:
nothing lies along them, which carves the silhouette.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np
import torch

from regnf.core.cameras import ray_aabb
from regnf.synthetic.sdfstudio_format import META_NAME, CaptureError


class CaptureLike(Protocol):
    """What the sample builder needs from a capture (``regnf.synthetic.sdfstudio_format.Capture``)."""

    width: int
    height: int
    frames: Sequence

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
    """(k, 3) origins of rays that hit nothing."""
    free_dirs: torch.Tensor
    """(k, 3) unit directions of rays that hit nothing."""


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
    h, w = depth.shape
    u = np.arange(w) + 0.5
    v = np.arange(h) + 0.5
    uu, vv = np.meshgrid(u, v)
    cam = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)
    R, t = camtoworld[:3, :3], camtoworld[:3, 3]
    d_world = cam @ R.T
    valid = np.isfinite(depth) & (depth > 0)
    z = np.where(valid, depth, 0.0)
    points = d_world * z[..., None] + t
    dirs = d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)
    return points, dirs, valid


def depth_normals(
    points: np.ndarray, depth: np.ndarray, valid: np.ndarray, K: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Normals (h, w, 3) from central differences of back-projected points, and a mask.

    A pixel's normal is trusted only when its 4 neighbours have depth and neither one-sided
    depth step exceeds ``8`` pixel footprints (a discontinuity, not a slanted surface).
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
    good = neigh & (steps < 8.0 * footprint) & (norm[..., 0] > 0)
    normals[c] = np.where(good[..., None], n, 0.0)
    ok[c] = good
    return normals, ok


def capture_where(capture: CaptureLike) -> str:
    """The capture's ``meta_data.json`` for messages (``capture`` for one without a root)."""
    root = getattr(capture, "root", None)
    return str(Path(root) / META_NAME) if root is not None else "capture"


def build_samples(capture: CaptureLike, indices: Sequence[int]) -> RGBDSamples:
    """Gather the samples of frames ``indices`` of ``capture`` (one pass per frame).

    Raises
    ------
    CaptureError
        A frame without depth, or the capture's own error for an invalid image or depth
        (:meth:`regnf.synthetic.sdfstudio_format.Capture.depth` names the file and the frame).
    """
    pts, cols, nrm, nok, org, tt, forg, fdir = [], [], [], [], [], [], [], []
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
        p, d, valid = backproject_frame(depth.astype(np.float64), K, c2w)
        n, ok = depth_normals(p, depth.astype(np.float64), valid, K, d)
        origin = c2w[:3, 3]
        pts.append(p[valid])
        cols.append(rgb[valid])
        nrm.append(n[valid])
        nok.append(ok[valid])
        org.append(np.broadcast_to(origin, (int(valid.sum()), 3)))
        tt.append(np.linalg.norm(p[valid] - origin, axis=-1))
        forg.append(np.broadcast_to(origin, (int((~valid).sum()), 3)))
        fdir.append(d[~valid])

    def cat(a: list, width: int | None = 3) -> torch.Tensor:
        arr = np.concatenate(a, 0) if a else np.zeros((0, width) if width else (0,))
        return torch.from_numpy(np.ascontiguousarray(arr)).float()

    return RGBDSamples(
        points=cat(pts), colors=cat(cols), normals=cat(nrm),
        normal_ok=torch.from_numpy(np.concatenate(nok, 0)) if nok else torch.zeros(0, dtype=torch.bool),
        origins=cat(org), ray_t=cat(tt, None), free_origins=cat(forg), free_dirs=cat(fdir),
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
