"""Headless RGB-D (+ instance id) rendering of coloured meshes.

Per frame:

- colour: pyrender with ``RenderFlags.FLAT`` (the shading is baked into face colours, see
  :mod:`regnf.synthetic.shading`), antialiased by pyrender's 4x MSAA at silhouettes;
- depth and instance ids: ray cast through the pixel centres (Open3D's ``RaycastingScene``),
  so they are exact there on every machine. They came from an OpenGL pass without
  multisampling before, which is exact at the pixel centres with Mesa but not with every driver:
  a capture rendered through another machine's driver had depth 1.7-2.6 mm (mean) from the
  true surface where Mesa's was within 0.003 mm, and its fields were 4x further off
  (docs/benchmarks.md, "GPU check").

Pixel convention: pixel (row v, column u) has its centre at image coordinates (u + 0.5, v + 0.5)
for the intrinsics K (as in nerfstudio / sdfstudio); pyrender's IntrinsicsCamera agrees.
"""

from __future__ import annotations

import os

from regnf.core.errors import RegnfError

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # headless; must precede the pyrender import

from collections.abc import Sequence

import numpy as np
import open3d as o3d
import pyrender
import torch
import trimesh

from regnf.core.cameras import opencv_to_opengl
from regnf.core.render_result import Render

VOID_GREY = (0.5, 0.5, 0.5)
"""Background colour of library captures ("in a void")."""

def _pyrender_mesh(mesh: trimesh.Trimesh) -> pyrender.Mesh:
    """A flat-shaded pyrender mesh; vertices are unmerged per face so colours do not bleed."""
    if mesh.visual.kind != "face":
        raise RegnfError("render: meshes must carry per-face colours (visual.kind == 'face')")
    positions = mesh.vertices[mesh.faces].reshape(-1, 3).astype(np.float32)
    colors = np.repeat(np.asarray(mesh.visual.face_colors, dtype=np.float32) / 255.0, 3, axis=0)
    normals = np.repeat(mesh.face_normals.astype(np.float32), 3, axis=0)
    material = pyrender.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0])
    prim = pyrender.Primitive(
        positions=positions, normals=normals, color_0=colors, material=material, mode=4
    )
    return pyrender.Mesh([prim])


class RGBDRenderer:
    """Renders a fixed set of meshes from many cameras, reusing one offscreen context.

    Use as a context manager (or call :meth:`delete`): the GL context must be released.

    Parameters
    ----------
    meshes : sequence of trimesh.Trimesh
        World-frame meshes with per-face colours (shading already baked).
    width, height : int
        Image size in pixels.
    instance_ids : sequence of int, optional
        Id of each mesh in the instance mask; -1 for unlabelled geometry. Defaults to all -1.
    bg_color : (3,) float
        Background colour in [0, 1].
    znear, zfar : float
        Clip planes (mesh units): of the colour pass, and the range a ray-cast hit must lie in
        to give a depth.
    """

    def __init__(
        self,
        meshes: Sequence[trimesh.Trimesh],
        width: int,
        height: int,
        instance_ids: Sequence[int] | None = None,
        bg_color: Sequence[float] = VOID_GREY,
        znear: float = 0.05,
        zfar: float = 50.0,
    ) -> None:
        if instance_ids is None:
            instance_ids = [-1] * len(meshes)
        if len(instance_ids) != len(meshes):
            raise RegnfError("render: one instance id per mesh is required")
        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = float(znear), float(zfar)
        self.scene = pyrender.Scene(bg_color=[*bg_color, 1.0], ambient_light=[1.0, 1.0, 1.0])
        self.rays = o3d.t.geometry.RaycastingScene()
        for mesh in meshes:
            self.scene.add(_pyrender_mesh(mesh))
            self.rays.add_triangles(
                o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
            )
        # Ray-cast geometry ids are the meshes' indices, in the order added; the last entry
        # is for a miss (mapped there below).
        self.instance_of = np.array([*(max(-1, int(i)) for i in instance_ids), -1], dtype=np.int64)
        self.camera = pyrender.IntrinsicsCamera(
            fx=1.0, fy=1.0, cx=0.5 * width, cy=0.5 * height, znear=self.znear, zfar=self.zfar
        )
        self.camera_node = self.scene.add(self.camera, pose=np.eye(4))
        self.renderer = pyrender.OffscreenRenderer(self.width, self.height)

    def render(self, camtoworld: np.ndarray, K: np.ndarray) -> Render:
        """Render one frame: colour, depth, mask and instance ids (CPU tensors; no normals).

        Parameters
        ----------
        camtoworld : (4, 4) float
            OpenCV cam-to-world pose (x right, y down, z forward).
        K : (3, 3) float
            Pinhole intrinsics; pixel centres at (u + 0.5, v + 0.5).

        Returns
        -------
        Render
            CPU tensors: ``rgb`` (H, W, 3) float32 ``uint8 / 255``
            (:func:`regnf.core.image_io.rgb_to_uint8` recovers the 8-bit image exactly),
            ``depth`` (H, W) float32 metres (0: nothing hit), ``mask`` ``depth > 0``,
            ``instance_id`` (H, W) int64 (-1: background or unlabelled geometry); no normals
            and no evaluation counts (None).
        """
        camtoworld = np.asarray(camtoworld, dtype=np.float64)
        K = np.asarray(K, dtype=np.float64)
        if camtoworld.shape != (4, 4) or K.shape != (3, 3):
            raise RegnfError(
                f"render: need a 4x4 pose and 3x3 K, got {camtoworld.shape}, {K.shape}"
            )
        self.camera.fx, self.camera.fy = float(K[0, 0]), float(K[1, 1])
        self.camera.cx, self.camera.cy = float(K[0, 2]), float(K[1, 2])
        self.scene.set_pose(self.camera_node, opencv_to_opengl(camtoworld))
        rgb, _ = self.renderer.render(self.scene, flags=pyrender.RenderFlags.FLAT)
        depth, ids = self._raycast(camtoworld, K)
        depth_t = torch.from_numpy(depth)
        return Render(
            rgb=torch.from_numpy(np.ascontiguousarray(rgb[..., :3])).float() / 255.0,
            depth=depth_t,
            normals=None,
            instance_id=torch.from_numpy(ids),
            mask=depth_t > 0,
            evals_per_pixel=None,
            lookups_per_pixel=None,
        )

    def _raycast(self, camtoworld: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z-depth (H, W) float32 (0: no hit within the clip planes) and instance ids (H, W)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        # Directions with a camera z of 1: the ray parameter of the hit is its z-depth.
        dirs = cam.reshape(-1, 3) @ camtoworld[:3, :3].T
        origins = np.broadcast_to(camtoworld[:3, 3], dirs.shape)
        hit = self.rays.cast_rays(o3d.core.Tensor(np.concatenate([origins, dirs], 1).astype(np.float32)))
        t = hit["t_hit"].numpy().reshape(self.height, self.width)
        # As the GL camera clips: nothing nearer than znear or beyond zfar.
        valid = np.isfinite(t) & (t >= self.znear) & (t <= self.zfar)
        gid = hit["geometry_ids"].numpy().astype(np.int64).reshape(self.height, self.width)
        gid = np.where(valid, gid, len(self.instance_of) - 1)
        return np.where(valid, t, 0.0).astype(np.float32), self.instance_of[gid]

    def delete(self) -> None:
        """Release the GL context (safe to call twice)."""
        if self.renderer is not None:
            self.renderer.delete()
            self.renderer = None

    def __enter__(self) -> RGBDRenderer:  # noqa: PYI034 (no typing.Self on 3.10)
        return self

    def __exit__(self, *exc: object) -> None:
        self.delete()
