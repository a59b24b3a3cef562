"""Cameras from ``UsdGeom.Camera`` prims, and compositor cameras authored as such prims.

USD's camera looks down its local -Z with +Y up and x right; the compositor's
(:mod:`regnf.render.camera`) looks down +Z with y down (OpenCV), so the camera axes differ by
a flip of y and z: ``opencv_to_world = usd_camera_to_world @ diag(1, -1, -1, 1)``.

Intrinsics: ``focalLength``, ``horizontalAperture``, ``verticalAperture`` and the aperture
offsets share one unit (tenths of a scene unit by USD's convention), so only their ratios
matter. The film window ``[offset - aperture / 2, offset + aperture / 2] / focalLength`` (at
unit depth, +y up; :class:`pxr.Gf.Frustum`'s window) spans the whole image of
``width x height`` pixels::

    fx = focalLength / horizontalAperture * width
    fy = focalLength / verticalAperture * height
    cx = width / 2 - horizontalApertureOffset / horizontalAperture * width
    cy = height / 2 + verticalApertureOffset / verticalAperture * height

(a positive vertical offset moves the window UP, so the principal point moves down the
image). A height matching the aperture's aspect ratio gives square pixels. USD stores these
attributes as 32-bit floats, so intrinsics survive a round trip to about 1e-7 relative.

Poses: the prim's local-to-world transform at ``time`` (``UsdGeom.XformCache``; its uniform
scale removed) with translations multiplied by the stage's ``metersPerUnit``. Poses are in
the stage's own world axes: nothing is rotated for its ``upAxis`` (pass ``up_axis`` to
require one).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom

from regnf.core.atomic_io import atomic_path
from regnf.core.cameras import OPENCV_TO_OPENGL, opencv_to_opengl
from regnf.core.errors import RegnfError
from regnf.render.camera import Camera
from regnf.scene_graph import StageError
from regnf.scene_graph.usd_read import open_stage

DEFAULT_HORIZONTAL_APERTURE = float(Gf.Camera.DEFAULT_HORIZONTAL_APERTURE)
"""Horizontal aperture authored by :func:`camera_to_usd` (USD's default, 35 mm academy)."""
DEFAULT_TIME = Usd.TimeCode.Default()
"""USD's default time: the attributes' default values, not their time samples."""
SCALE_TOLERANCE = 1e-6
"""Largest deviation from a rotation allowed of a camera's transform once its uniform scale is removed."""


def _time(time: Usd.TimeCode | float) -> Usd.TimeCode:
    return time if isinstance(time, Usd.TimeCode) else Usd.TimeCode(float(time))


def _path_problem(path: str) -> str | None:
    """Why ``path`` is not an absolute prim path, or None if it is one."""
    valid = Sdf.Path.IsValidPathString(path)  # truthy, or falsy with an errorMessage
    if not valid:
        return f"not a valid path: {valid.errorMessage}"
    if not Sdf.Path(path).IsAbsolutePath() or not Sdf.Path(path).IsPrimPath():
        return "not an absolute prim path"
    return None


def _camera_prim(stage: Usd.Stage, file: str, path: str) -> Usd.Prim:
    """The ``UsdGeom.Camera`` prim at ``path``; ``StageError`` naming the file and prim otherwise."""
    problem = _path_problem(path)
    if problem is not None:
        raise StageError(file, path, problem)
    prim = stage.GetPrimAtPath(path)
    if not prim:
        raise StageError(file, path, "no such prim")
    if not prim.IsA(UsdGeom.Camera):
        kind = prim.GetTypeName() or "typeless prim"
        raise StageError(file, path, f"is a {kind}, not a UsdGeom.Camera")
    return prim


def _rigid(M: np.ndarray, file: str, path: str) -> np.ndarray:
    """(4, 4) ``M`` (column vectors) with its uniform scale removed; refuses shear, reflection, projection."""
    if not np.isfinite(M).all() or np.abs(M[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-12:
        raise StageError(file, path, f"the camera's transform is not affine and finite: {M.tolist()}")
    A = M[:3, :3]
    det = float(np.linalg.det(A))
    if not det > 1e-300:
        raise StageError(file, path, f"the camera's transform is degenerate or mirrored (det {det:.6g})")
    R = A / np.cbrt(det)
    if np.abs(R.T @ R - np.eye(3)).max() > SCALE_TOLERANCE:
        raise StageError(file, path, "the camera's transform has a non-uniform scale or a shear")
    U, _, Vt = np.linalg.svd(R)  # the nearest rotation (R is one up to rounding)
    out = np.eye(4)
    out[:3, :3] = U @ Vt
    out[:3, 3] = M[:3, 3]
    return out


def _intrinsics(
    cam: Gf.Camera, width: int, height: int | None, file: str, path: str
) -> tuple[np.ndarray, int]:
    """(3, 3) float64 ``K`` and the image height of a perspective ``Gf.Camera`` (see the module)."""
    if cam.projection != Gf.Camera.Perspective:
        raise StageError(file, path, f"projection is {cam.projection}, only perspective cameras are supported")
    f, ha, va = float(cam.focalLength), float(cam.horizontalAperture), float(cam.verticalAperture)
    ox, oy = float(cam.horizontalApertureOffset), float(cam.verticalApertureOffset)
    if not all(np.isfinite([f, ha, va, ox, oy])) or min(f, ha, va) <= 0.0:
        raise StageError(file, path, f"needs finite focalLength and apertures > 0, got focalLength {f}, "
                                     f"apertures {ha} x {va}, offsets ({ox}, {oy})")
    h = max(1, round(width * va / ha)) if height is None else int(height)
    K = np.array([
        [f / ha * width, 0.0, width / 2.0 - ox / ha * width],
        [0.0, f / va * h, h / 2.0 + oy / va * h],
        [0.0, 0.0, 1.0],
    ])
    return K, h


def camera_prims(stage: Usd.Stage) -> list[str]:
    """Paths of every ``UsdGeom.Camera`` prim of ``stage``, in traversal (depth-first) order."""
    return [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]


def cameras_from_usd(
    stage_path: str | os.PathLike,
    prims: Sequence[str] | None = None,
    width: int | None = None,
    height: int | None = None,
    time: Usd.TimeCode | float = DEFAULT_TIME,
    up_axis: str | None = None,
) -> list[Camera]:
    """The cameras of ``UsdGeom.Camera`` prims of a stage, posed in metres, OpenCV axes.

    Parameters
    ----------
    stage_path : str or PathLike
        A stage (.usda, .usdc, .usdz).
    prims : sequence of str, optional
        Absolute prim paths, in this order; None: every camera prim, in traversal order.
    width : int
        Image width in pixels (required: USD cameras have no pixel size).
    height : int, optional
        Image height in pixels; None: from the aperture's aspect ratio (square pixels).
    time : Usd.TimeCode or float
        Time of the transforms and camera attributes.
    up_axis : {"Y", "Z"}, optional
        Require the stage's ``upAxis`` (the poses are in the stage's own axes).

    Returns
    -------
    list of Camera
        One per prim; ``K`` (3, 3) and ``camera_to_world`` (4, 4) in metres.

    Raises
    ------
    scene_graph.StageError
        A ``ValueError`` naming the stage and the prim: a stage that cannot be opened, a missing
        prim, a prim that is not a camera, a stage without cameras, an orthographic camera,
        a transform with shear or non-uniform scale, another ``upAxis`` than ``up_axis``.
    ValueError
        No width, a size < 1, an empty ``prims``.
    """
    bad_height = height is not None and (int(height) != height or height < 1)
    if width is None or int(width) != width or width < 1 or bad_height:
        raise RegnfError(f"need an integer width >= 1 (and height >= 1 or None), got {width} x {height}")
    if prims is not None and len(prims) == 0:
        raise RegnfError("no camera prim given")
    file = str(Path(stage_path).absolute())
    stage = open_stage(file)
    if up_axis is not None and UsdGeom.GetStageUpAxis(stage) != up_axis:
        raise StageError(file, "/", f"upAxis is {UsdGeom.GetStageUpAxis(stage)}, expected {up_axis}")
    paths = camera_prims(stage) if prims is None else [str(p) for p in prims]
    if not paths:
        raise StageError(file, "/", "the stage holds no UsdGeom.Camera prim")
    metres = float(UsdGeom.GetStageMetersPerUnit(stage))
    t = _time(time)
    cache = UsdGeom.XformCache(t)
    cams = []
    for path in paths:  # a handful of cameras
        prim = _camera_prim(stage, file, path)
        K, h = _intrinsics(UsdGeom.Camera(prim).GetCamera(t), int(width), height, file, path)
        pose = _rigid(np.array(cache.GetLocalToWorldTransform(prim)).T, file, path) @ OPENCV_TO_OPENGL
        pose[:3, 3] *= metres
        cams.append(Camera(K, int(width), h, pose))
    return cams


def camera_to_usd(stage: Usd.Stage, path: str, camera: Camera) -> UsdGeom.Camera:
    """Author ``camera`` as a perspective ``UsdGeom.Camera`` at ``path`` (inverse of :func:`cameras_from_usd`).

    The horizontal aperture is USD's default (20.955); the focal length, vertical aperture
    and offsets follow from ``K`` and the image size. The pose (metres) is divided by the
    stage's ``metersPerUnit`` and authored as one ``xformOp:transform`` relative to the
    parent prim's world transform (default time), replacing any earlier transform ops.
    Nothing is saved: the caller saves or exports the stage.

    Parameters
    ----------
    stage : Usd.Stage
        The stage to author in (its current edit target).
    path : str
        Absolute prim path; an existing prim must be a camera (or typeless).
    camera : Camera
        ``K`` without skew (3, 3) and ``camera_to_world`` (4, 4) metres, OpenCV axes.

    Returns
    -------
    UsdGeom.Camera
        The authored camera.

    Raises
    ------
    ValueError
        ``K`` with skew or a non-positive focal length, a bad path or a prim of another type.
    """
    K = camera.K
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    pinhole = K[0, 1] == 0.0 and K[1, 0] == 0.0 and np.array_equal(K[2], [0.0, 0.0, 1.0])
    if not pinhole or min(fx, fy) <= 0:
        raise RegnfError(f"a USD camera needs K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                         f"got {K.tolist()}")
    problem = _path_problem(path)
    if problem is not None:
        raise RegnfError(f"{path!r}: {problem}")
    existing = stage.GetPrimAtPath(path)
    if existing and existing.GetTypeName() not in ("", "Camera"):
        raise RegnfError(f"prim {path} exists and is a {existing.GetTypeName()}, not a Camera")
    W, H = camera.width, camera.height
    ha = DEFAULT_HORIZONTAL_APERTURE
    f = fx * ha / W
    usd_cam = UsdGeom.Camera.Define(stage, path)
    usd_cam.CreateProjectionAttr().Set(UsdGeom.Tokens.perspective)
    usd_cam.CreateFocalLengthAttr().Set(f)
    usd_cam.CreateHorizontalApertureAttr().Set(ha)
    usd_cam.CreateVerticalApertureAttr().Set(f * H / fy)
    usd_cam.CreateHorizontalApertureOffsetAttr().Set((W / 2.0 - cx) / fx * f)
    usd_cam.CreateVerticalApertureOffsetAttr().Set((cy - H / 2.0) / fy * f)

    world = opencv_to_opengl(camera.camera_to_world)
    world[:3, 3] /= float(UsdGeom.GetStageMetersPerUnit(stage))
    parent = usd_cam.GetPrim().GetParent()
    cache = UsdGeom.XformCache(DEFAULT_TIME)
    to_parent = np.eye(4)
    if parent.IsA(UsdGeom.Xformable):
        to_parent = np.array(cache.GetLocalToWorldTransform(parent)).T
    local = np.linalg.solve(to_parent, world)
    usd_cam.MakeMatrixXform().Set(Gf.Matrix4d(local.T.tolist()))
    return usd_cam


def write_cameras_usd(
    path: str | os.PathLike, cameras: Sequence[Camera], parent: str = "/Cameras"
) -> Path:
    """Write ``cameras`` into a new stage (Z up, metres) as ``{parent}/view_0000``, ``view_0001``, ..., atomically.

    Parameters
    ----------
    path : str or PathLike
        A .usda, .usdc or .usd file; its folder must exist. Replaced if present.
    cameras : sequence of Camera
        At least one.
    parent : str
        Absolute path of the ``Scope`` holding the cameras.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    if len(cameras) == 0:
        raise RegnfError("no camera to write")
    if not path.parent.is_dir():
        raise RegnfError(f"cannot write {path}: folder {path.parent} does not exist")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    problem = _path_problem(parent)
    if problem is not None:
        raise RegnfError(f"parent {parent!r}: {problem}")
    UsdGeom.Scope.Define(stage, parent)
    stage.SetDefaultPrim(stage.GetPrimAtPath(Sdf.Path(parent).GetPrefixes()[0]))
    for k, cam in enumerate(cameras):  # a handful of cameras
        camera_to_usd(stage, f"{parent}/view_{k:04d}", cam)
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise StageError(path, "/", "USD could not export the stage")
    return path
