"""nerfstudio's ``transforms.json`` for a rendered folder, so that renders are training data.

nerfstudio expects ``transform_matrix`` as camera-to-world in the OpenGL / Blender camera
convention (x right, y UP, z BACKWARDS, the camera looks along -z); the compositor's cameras
are OpenCV (x right, y down, z forward). The two differ by a rotation of pi about the
camera's x axis: ``c2w_gl = c2w_cv @ diag(1, -1, -1, 1)``. The pinhole intrinsics are the
same numbers in both (nerfstudio also samples pixel centres at ``u + 0.5``). Depth images are
16-bit millimetres (nerfstudio's default ``depth_unit_scale_factor`` of 1e-3 reads them as
metres). The instance images are not given as nerfstudio's ``mask_path``: nerfstudio
leaves out every pixel whose mask is 0, and an instance image is 0 on the room itself; they
are listed per frame as ``instance_file_path`` instead.
"""

from __future__ import annotations

from collections.abc import Sequence

from regnf.core.cameras import opencv_to_opengl
from regnf.core.errors import RegnfError
from regnf.render.camera import Camera

from .render_folder import ViewFiles


def intrinsics_json(camera: Camera) -> dict:
    """nerfstudio's pinhole keys for ``camera``."""
    K = camera.K
    return {
        "fl_x": float(K[0, 0]),
        "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "w": camera.width,
        "h": camera.height,
    }


def transforms_json(cameras: Sequence[Camera], views: Sequence[ViewFiles], extra: dict | None = None) -> dict:
    """The ``transforms.json`` content of rendered views.

    Shared intrinsics go at the top level (nerfstudio's usual layout); if the cameras differ,
    every frame carries its own. ``extra`` lands under the key ``regnf``.

    Parameters
    ----------
    cameras : sequence of Camera
        Posed in metres, OpenCV axes.
    views : sequence of ViewFiles
        The files of each camera, relative to the folder of ``transforms.json``.
    extra : dict, optional
    """
    if len(cameras) != len(views) or len(cameras) == 0:
        raise RegnfError(f"need one file set per camera and at least one, got {len(cameras)} and {len(views)}")
    intr = [intrinsics_json(c) for c in cameras]
    shared = all(i == intr[0] for i in intr)
    frames = []
    for cam, files, i in zip(cameras, views, intr, strict=True):  # a loop over views
        frame = {
            "file_path": files.rgb,
            "depth_file_path": files.depth,
            "instance_file_path": files.instance,
            "transform_matrix": opencv_to_opengl(cam.camera_to_world).tolist(),
        }
        frames.append(frame if shared else {**i, **frame})
    data: dict = {"camera_model": "OPENCV"}
    if shared:
        data.update(intr[0])
    data["frames"] = frames
    if extra:
        data["regnf"] = extra
    return data
