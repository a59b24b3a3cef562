"""Headless RGB-D (+ instance id) rendering of coloured meshes with pyrender.

Two passes per frame:
- colour: ``RenderFlags.FLAT`` (the shading is baked into face colours, see
  :mod:`regnf.synthetic.shading`), antialiased by pyrender's 4x MSAA at silhouettes;
- segmentation: ``RenderFlags.SEG`` renders with multisampling disabled, so its depth and ids
  are exact at pixel centres. Depth is read from THIS pass: the MSAA depth resolve of the colour
  pass returns one sub-sample, not the pixel centre.

Pixel convention: pixel (row v, column u) has its centre at image coordinates (u + 0.5, v + 0.5)
for the intrinsics K (as in nerfstudio / sdfstudio); pyrender's IntrinsicsCamera agrees.
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # headless; must precede the pyrender import

from collections.abc import Sequence

import numpy as np
import pyrender
import torch
import trimesh

from regnf.core.cameras import opencv_to_opengl
from regnf.core.render_result import Render

VOID_GREY = (0.5, 0.5, 0.5)
"""Background colour of library captures ("in a void")."""

_BACKGROUND_CODE = 0
_UNLABELLED_CODE = 1  # geometry without an instance id (floor, walls, clutter)


def _code_to_color(code: int) -> np.ndarray:
    """Segmentation colour (3,) encoding a 24-bit integer in 8-bit RGB (pyrender divides by 255)."""
    return np.array([code & 255, (code >> 8) & 255, (code >> 16) & 255], dtype=np.float64)


def _color_to_code(seg: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 segmentation image -> (H, W) int64 codes."""
    seg = seg.astype(np.int64)
    return seg[..., 0] + (seg[..., 1] << 8) + (seg[..., 2] << 16)


def _pyrender_mesh(mesh: trimesh.Trimesh) -> pyrender.Mesh:
    """A flat-shaded pyrender mesh; vertices are unmerged per face so colours do not bleed."""
    if mesh.visual.kind != "face":
        raise ValueError("render: meshes must carry per-face colours (visual.kind == 'face')")
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
        Clip planes (mesh units); a larger ``znear`` gives a more precise depth buffer.
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
            raise ValueError("render: one instance id per mesh is required")
        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = float(znear), float(zfar)
        self.scene = pyrender.Scene(bg_color=[*bg_color, 1.0], ambient_light=[1.0, 1.0, 1.0])
        self.seg_map: dict = {}
        for mesh, iid in zip(meshes, instance_ids):
            node = self.scene.add(_pyrender_mesh(mesh))
            code = _UNLABELLED_CODE if iid < 0 else int(iid) + 2
            self.seg_map[node] = _code_to_color(code)
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
            raise ValueError(
                f"render: need a 4x4 pose and 3x3 K, got {camtoworld.shape}, {K.shape}"
            )
        self.camera.fx, self.camera.fy = float(K[0, 0]), float(K[1, 1])
        self.camera.cx, self.camera.cy = float(K[0, 2]), float(K[1, 2])
        self.scene.set_pose(self.camera_node, opencv_to_opengl(camtoworld))
        rgb, _ = self.renderer.render(self.scene, flags=pyrender.RenderFlags.FLAT)
        seg, depth = self.renderer.render(
            self.scene, flags=pyrender.RenderFlags.SEG, seg_node_map=self.seg_map
        )
        ids = _color_to_code(seg) - 2
        ids[ids < 0] = -1
        depth_t = torch.from_numpy(depth.astype(np.float32))
        return Render(
            rgb=torch.from_numpy(np.ascontiguousarray(rgb[..., :3])).float() / 255.0,
            depth=depth_t,
            normals=None,
            instance_id=torch.from_numpy(ids),
            mask=depth_t > 0,
            evals_per_pixel=None,
            lookups_per_pixel=None,
        )

    def delete(self) -> None:
        """Release the GL context (safe to call twice)."""
        if self.renderer is not None:
            self.renderer.delete()
            self.renderer = None

    def __enter__(self) -> RGBDRenderer:  # noqa: PYI034 (no typing.Self on 3.10)
        return self

    def __exit__(self, *exc: object) -> None:
        self.delete()
