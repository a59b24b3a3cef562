"""Quality of a trained field against ground truth: surface error, Chamfer, held-out PSNR.

Distances are reported relative to the diagonal of the object's bounding box (metres /
metres), so numbers compare across objects of any size. For a scene, each furniture
instance is measured against its own diagonal.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.meshes.meshing import extract_mesh
from regnf.observations.rgbd_samples import capture_where
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.render.sphere_tracer import SphereTracerConfig


class SurfaceError(NamedTuple):
    """|SDF| of a field at ground-truth surface samples, relative to the diagonal."""

    mean_rel: float
    p95_rel: float


def world_to_field(field: Field, points_m: np.ndarray) -> torch.Tensor:
    """Map points (n, 3) in metres into the field frame (float32 tensor on the field's device)."""
    M = field.to_world.detach().cpu().double().numpy()
    local = (points_m - M[:3, 3]) @ np.linalg.inv(M[:3, :3]).T
    return torch.from_numpy(local).float().to(field.device)


def surface_samples(mesh: trimesh.Trimesh, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points spread evenly over the mesh surface (deterministic for ``seed``)."""
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts)


def relative_surface_errors(field: Field, points_m: np.ndarray, diag_m: float | np.ndarray) -> np.ndarray:
    """(n,) |SDF| in metres at ``points_m`` divided by the diagonal(s) ``diag_m``."""
    sdf = field.sdf_chunked(world_to_field(field, points_m)).abs().cpu().double().numpy()
    return sdf * field.world_scale / np.asarray(diag_m, dtype=np.float64)


def surface_error(
    field: Field, meshes_m: Sequence[trimesh.Trimesh], n_per_mesh: int = 20000, seed: int = 0
) -> SurfaceError:
    """Surface error of ``field`` over one or more ground-truth meshes (each its own diagonal)."""
    errs = []
    for i, mesh in enumerate(meshes_m):
        diag = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
        errs.append(relative_surface_errors(field, surface_samples(mesh, n_per_mesh, seed + i), diag))
    e = np.concatenate(errs)
    return SurfaceError(float(e.mean()), float(np.percentile(e, 95)))


def chamfer_relative(
    field: Field,
    meshes_m: Sequence[trimesh.Trimesh],
    resolution: int = 192,
    n_samples: int = 20000,
    pad_rel: float = 0.05,
    seed: int = 0,
) -> float:
    """Symmetric Chamfer distance between the field's mesh and each ground-truth mesh.

    The field is meshed (marching cubes) inside each ground-truth mesh's box, grown by
    ``pad_rel`` of its diagonal, which is where a scene's furniture is; the result is the
    mean over meshes of (mean nearest distance both ways) / 2 / diagonal.
    """
    M = field.to_world.detach().cpu().double().numpy()
    Minv = np.linalg.inv(M)
    scores = []
    for i, gt in enumerate(meshes_m):
        lo, hi = gt.bounds
        diag = float(np.linalg.norm(hi - lo))
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        corners = corners + np.sign(corners - (lo + hi) / 2) * pad_rel * diag
        local = corners @ Minv[:3, :3].T + Minv[:3, 3]
        box = np.stack([local.min(0), local.max(0)])
        fb = field.bounds.detach().cpu().numpy()
        box = np.stack([np.maximum(box[0], fb[0]), np.minimum(box[1], fb[1])])
        # Resolution scales with the box so that the cell size matches the field's own mesh.
        mesh = extract_mesh(field, resolution=resolution, bounds=box, with_color=False, in_world=True)
        pred, _ = trimesh.sample.sample_surface(mesh, n_samples, seed=seed + i)
        true, _ = trimesh.sample.sample_surface(gt, n_samples, seed=seed + i)
        inside = np.all((pred >= lo - pad_rel * diag) & (pred <= hi + pad_rel * diag), axis=1)
        pred = pred[inside] if inside.any() else pred
        d_pt = cKDTree(true).query(pred)[0].mean()
        d_tp = cKDTree(pred).query(true)[0].mean()
        scores.append(0.5 * (d_pt + d_tp) / diag)
    return float(np.mean(scores))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) between two images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def heldout_psnr(
    field: Field,
    capture,
    indices: Sequence[int] | None = None,
    supersample: int = 2,
    background: Sequence[float] = (0.5, 0.5, 0.5),
) -> tuple[float, list[np.ndarray]]:
    """Mean PSNR of field renders against the capture's held-out frames, and the renders.

    Renders are supersampled (``supersample``^2 rays per pixel through a regular sub-grid,
    box filtered) because the ground-truth colour images are multisample anti-aliased. Each
    view is rendered by :func:`~regnf.render.sphere_render.render` from the frame's
    camera in metres (so any field of the object, in any frame, can be measured).

    Raises
    ------
    ValueError
        No held-out frame, a bad ``supersample``, or a held-out frame with lens distortion:
        :class:`~regnf.render.camera.Camera` is a pinhole, so its render and the
        distorted photo would not line up (refused rather than scored wrong).
    """
    idx = list(capture.test_indices() if indices is None else indices)
    if not idx:
        raise RegnfError("the capture has no held-out frames")
    if int(supersample) != supersample or supersample < 1:
        raise RegnfError(f"supersample must be a positive integer, got {supersample}")
    distorted = [i for i in idx if getattr(capture.frames[i], "distortion", None) is not None]
    if distorted:
        i = distorted[0]
        raise RegnfError(
            f"{capture_where(capture)}: held-out frame {i} has lens distortion "
            f"({capture.frames[i].distortion.describe()}); held-out PSNR renders pinhole views and "
            "cannot compare them with distorted images: undistort the capture's images first"
        )
    s, w, h = int(supersample), capture.width, capture.height
    config = SphereTracerConfig(background=tuple(background), check_camera=False)
    # Rendering s times larger with K scaled by s samples each pixel (u, v) at the centres of an
    # s x s sub-grid, u + (j + 0.5) / s: the box filter is then a mean over s x s blocks.
    scale = np.diag([float(s), float(s), 1.0])
    scores, images = [], []
    for i in idx:
        cam = Camera(scale @ capture.frames[i].intrinsics, w * s, h * s, capture.camtoworld_metres(i))
        out = render(field, cam, config)
        img = out.rgb.detach().cpu().double().reshape(h, s, w, s, 3).mean(dim=(1, 3)).numpy()
        images.append(img)
        scores.append(psnr(img, capture.rgb(i)))
    return float(np.mean(scores)), images
