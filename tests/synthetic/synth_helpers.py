"""Shared helpers for the synthetic-data tests: independent ray casts with Open3D.

A plain module with a unique name (not ``conftest``), imported by the test modules.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d
import trimesh


def raycast(
    meshes: Sequence[trimesh.Trimesh],
    camtoworld: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """z-depth (H, W) float (inf = miss) and geometry index (H, W) int (-1 = miss) through pixel
    centres (u + 0.5, v + 0.5), cast with Open3D's RaycastingScene (independent of pyrender)."""
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(
            o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(m.faces, dtype=np.uint32)),
        )
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    cam_dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    # Unnormalised directions with camera-z = 1: the ray parameter IS the z-depth.
    dirs = cam_dirs.reshape(-1, 3) @ camtoworld[:3, :3].T
    origins = np.broadcast_to(camtoworld[:3, 3], dirs.shape)
    rays = o3d.core.Tensor(np.concatenate([origins, dirs], 1).astype(np.float32))
    hit = scene.cast_rays(rays)
    t = hit["t_hit"].numpy().reshape(height, width).astype(np.float64)
    gid = hit["geometry_ids"].numpy().astype(np.int64).reshape(height, width)
    gid[~np.isfinite(t)] = -1
    return t, gid


def erode(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """Binary erosion with a 3x3 cross, pixels outside the image count as False."""
    out = mask.copy()
    for _ in range(iterations):
        p = np.pad(out, 1, constant_values=False)
        out = p[1:-1, 1:-1] & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return out


def backproject(depth: np.ndarray, camtoworld: np.ndarray, K: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) of z-depth pixels (pixel centres)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    cam = cam * depth[..., None]
    return cam @ camtoworld[:3, :3].T + camtoworld[:3, 3]
