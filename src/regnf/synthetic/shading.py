"""Baked, view-independent Lambertian shading.

The data set's colour must not depend on the viewing direction (the fields' colour heads are
trained and compared across views), so the shading is baked into per-face colours once, with a
fixed light in the WORLD frame, and images are rendered with flat (unlit) shading. Library
captures and rooms use this same function, so a chair in a room and in the void is lit alike
when it has the same orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass(frozen=True)
class ShadingConfig:
    """A fixed directional light plus ambient term."""

    light_dir: tuple[float, float, float] = (0.35, 0.25, 1.0)
    """Direction TOWARDS the light in the world frame (normalised on use): above, slightly front."""
    ambient: float = 0.45
    """Ambient fraction of the albedo, seen on every face."""
    diffuse: float = 0.55
    """Lambertian weight, multiplied by max(0, n . l)."""


def shade_face_colors(
    face_normals: np.ndarray, albedo: np.ndarray, config: ShadingConfig = ShadingConfig()
) -> np.ndarray:
    """Shaded colours ``albedo * (ambient + diffuse * max(0, n . l))``.

    Parameters
    ----------
    face_normals : (F, 3) float
        Unit outward face normals in the world frame.
    albedo : (F, 3) or (F, 4) uint8
        Face albedos (alpha, if present, is kept).

    Returns
    -------
    (F, 4) uint8
        Shaded RGBA colours.
    """
    light = np.asarray(config.light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    factor = config.ambient + config.diffuse * np.clip(face_normals @ light, 0.0, None)
    rgb = np.clip(np.round(albedo[:, :3].astype(np.float64) * factor[:, None]), 0, 255)
    alpha = albedo[:, 3:4] if albedo.shape[1] == 4 else np.full((len(albedo), 1), 255)
    return np.concatenate([rgb, alpha], axis=1).astype(np.uint8)


def shaded_copy(mesh: trimesh.Trimesh, config: ShadingConfig = ShadingConfig()) -> trimesh.Trimesh:
    """A copy of ``mesh`` (already in the world frame) whose face colours carry baked shading."""
    out = mesh.copy()
    out.visual.face_colors = shade_face_colors(
        np.asarray(mesh.face_normals), np.asarray(mesh.visual.face_colors), config
    )
    return out
