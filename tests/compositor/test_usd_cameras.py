"""Cameras read from and written to ``UsdGeom.Camera`` prims."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from regnf.compositor import Camera, look_at
from regnf.compositor.usd_cameras import camera_to_usd, cameras_from_usd, write_cameras_usd
from regnf.scene_graph import StageError


def new_stage(path: Path, meters_per_unit: float = 1.0, up: str = "Z") -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    return stage


def random_cameras(rng: np.random.Generator, n: int) -> list[Camera]:
    """Cameras with non-square pixels, off-centre principal points and arbitrary poses."""
    cams = []
    for _ in range(n):
        w, h = int(rng.integers(16, 640)), int(rng.integers(16, 480))
        K = np.array([[rng.uniform(50, 900), 0.0, rng.uniform(0, w)],
                      [0.0, rng.uniform(50, 900), rng.uniform(0, h)],
                      [0.0, 0.0, 1.0]])
        eye = rng.uniform(-5, 5, 3)
        cams.append(Camera(K, w, h, look_at(eye, eye + rng.normal(size=3))))
    return cams


def project(camera: Camera, point: np.ndarray) -> np.ndarray:
    """(2,) pixel coordinates (continuous, pixel centres at + 0.5) of a world point."""
    p = np.linalg.solve(camera.camera_to_world, [*point, 1.0])[:3]
    uvw = camera.K @ p
    return uvw[:2] / uvw[2]


def test_round_trip(tmp_path: Path) -> None:
    cams = random_cameras(np.random.default_rng(3), 6)
    file = write_cameras_usd(tmp_path / "cams.usda", cams)
    for k, cam in enumerate(cams):
        (back,) = cameras_from_usd(file, [f"/Cameras/view_{k:04d}"], cam.width, cam.height)
        assert (back.width, back.height) == (cam.width, cam.height)
        np.testing.assert_allclose(back.camera_to_world, cam.camera_to_world, rtol=0, atol=1e-9)
        # USD stores focal length and apertures as 32-bit floats.
        np.testing.assert_allclose(back.K, cam.K, rtol=1e-6, atol=1e-9)
    # All the cameras, in traversal order; square pixels give the height back from the aspect.
    square = Camera(np.array([[300.0, 0, 160.0], [0, 300.0, 120.0], [0, 0, 1]]), 320, 240, look_at((1, 2, 3), (0, 0, 0)))
    file = write_cameras_usd(tmp_path / "two.usdc", [cams[0], square])
    both = cameras_from_usd(file, width=320)
    assert [c.height for c in both] == [round(320 * cams[0].height * cams[0].K[0, 0] / (cams[0].width * cams[0].K[1, 1])), 240]
    np.testing.assert_allclose(both[1].K, square.K, rtol=1e-6)
    np.testing.assert_allclose(both[1].camera_to_world, square.camera_to_world, atol=1e-9)


def test_round_trip_in_centimetres_under_a_moved_parent(tmp_path: Path) -> None:
    """Translations go through metersPerUnit; the parent's transform is undone when authoring."""
    stage = new_stage(tmp_path / "cm.usda", meters_per_unit=0.01)
    rig = UsdGeom.Xform.Define(stage, "/Rig")
    rig.AddTranslateOp().Set(Gf.Vec3d(120.0, -40.0, 7.0))
    rig.AddRotateZOp().Set(33.0)
    rig.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))  # a uniform scale does not change what a camera sees
    (cam,) = random_cameras(np.random.default_rng(8), 1)
    camera_to_usd(stage, "/Rig/cam", cam)
    camera_to_usd(stage, "/Rig/cam", cam)  # authoring again replaces, does not stack
    stage.Save()
    (back,) = cameras_from_usd(tmp_path / "cm.usda", ["/Rig/cam"], cam.width, cam.height)
    np.testing.assert_allclose(back.camera_to_world, cam.camera_to_world, atol=1e-9)
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-6)
    world = np.array(UsdGeom.XformCache().GetLocalToWorldTransform(stage.GetPrimAtPath("/Rig/cam"))).T
    np.testing.assert_allclose(world[:3, 3] * 0.01, cam.center, atol=1e-9)  # stage units are centimetres


def hand_made_stage(path: Path, meters_per_unit: float = 1.0) -> Usd.Stage:
    """Cameras at (0, -3, 1) m looking along +Y (world +Z up), authored with plain pxr calls."""
    stage = new_stage(path, meters_per_unit)
    for name, offsets in (("plain", (0.0, 0.0)), ("shifted", (3.6, 2.4))):
        cam = UsdGeom.Camera.Define(stage, f"/World/{name}")
        cam.AddTranslateOp().Set(Gf.Vec3d(0.0, -3.0, 1.0) / meters_per_unit)
        cam.AddRotateXOp().Set(90.0)  # USD cameras look down -Z with +Y up: now along +Y with +Z up
        cam.CreateFocalLengthAttr(24.0)
        cam.CreateHorizontalApertureAttr(36.0)
        cam.CreateVerticalApertureAttr(24.0)
        cam.CreateHorizontalApertureOffsetAttr(offsets[0])
        cam.CreateVerticalApertureOffsetAttr(offsets[1])
    UsdGeom.Xform.Define(stage, "/World/Box")
    stage.Save()
    return stage


@pytest.mark.parametrize("meters_per_unit", [1.0, 0.01])
def test_a_hand_made_camera(tmp_path: Path, meters_per_unit: float) -> None:
    stage = hand_made_stage(tmp_path / "hand.usda", meters_per_unit)
    plain, shifted = cameras_from_usd(tmp_path / "hand.usda", width=300)  # traversal order
    expected_pose = look_at((0.0, -3.0, 1.0), (0.0, 0.0, 1.0), up=(0.0, 0.0, 1.0))
    for cam in (plain, shifted):
        assert (cam.width, cam.height) == (300, 200)  # height from the 36 x 24 aperture
        np.testing.assert_allclose(cam.camera_to_world, expected_pose, atol=1e-9)
    # fx = 24 / 36 * 300; a positive offset moves the film window right / up.
    np.testing.assert_allclose(plain.K, [[200.0, 0, 150.0], [0, 200.0, 100.0], [0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(shifted.K, [[200.0, 0, 120.0], [0, 200.0, 120.0], [0, 0, 1]], rtol=1e-6)
    # A point 5 m ahead, 0.5 m right and 0.25 m up.
    point = np.array([0.5, 2.0, 1.25])
    np.testing.assert_allclose(project(plain, point), [170.0, 90.0], atol=1e-9)
    np.testing.assert_allclose(project(shifted, point), [140.0, 110.0], atol=1e-4)
    # pxr's own projection (GfFrustum, in stage units) lands on the same pixels.
    for name, cam in (("plain", plain), ("shifted", shifted)):
        frustum = UsdGeom.Camera(stage.GetPrimAtPath(f"/World/{name}")).GetCamera(Usd.TimeCode.Default()).frustum
        view_proj = frustum.ComputeViewMatrix() * frustum.ComputeProjectionMatrix()
        ndc = view_proj.Transform(Gf.Vec3d(*(point / meters_per_unit)))
        pixel = [(ndc[0] + 1.0) / 2.0 * cam.width, (1.0 - ndc[1]) / 2.0 * cam.height]
        np.testing.assert_allclose(project(cam, point), pixel, atol=1e-4)


def test_an_animated_camera(tmp_path: Path) -> None:
    stage = new_stage(tmp_path / "anim.usda")
    cam = UsdGeom.Camera.Define(stage, "/cam")
    op = cam.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 1), 1.0)
    op.Set(Gf.Vec3d(0, 0, 3), 2.0)
    stage.Save()
    for t, z in ((1.0, 1.0), (2.0, 3.0), (Usd.TimeCode(1.5), 2.0)):
        (c,) = cameras_from_usd(tmp_path / "anim.usda", width=64, time=t)
        np.testing.assert_allclose(c.center, [0, 0, z], atol=1e-12)
        np.testing.assert_allclose(c.camera_to_world[:3, 2], [0, 0, -1], atol=1e-12)  # looks down -Z


def test_errors_name_the_stage_and_the_prim(tmp_path: Path) -> None:
    file = tmp_path / "hand.usda"
    hand_made_stage(file)
    where = str(file.absolute())
    with pytest.raises(StageError, match=rf"{where}: prim /World/Box: is a Xform, not a UsdGeom.Camera"):
        cameras_from_usd(file, ["/World/plain", "/World/Box"], width=32)
    with pytest.raises(ValueError, match=rf"{where}: prim /World/nope: no such prim"):
        cameras_from_usd(file, ["/World/nope"], width=32)
    with pytest.raises(ValueError, match=r"prim World/plain: not an absolute prim path"):
        cameras_from_usd(file, ["World/plain"], width=32)
    with pytest.raises(ValueError, match=r"upAxis is Z, expected Y"):
        cameras_from_usd(file, width=32, up_axis="Y")
    with pytest.raises(ValueError, match="integer width"):
        cameras_from_usd(file)
    empty = tmp_path / "empty.usda"
    stage = new_stage(empty)
    UsdGeom.Xform.Define(stage, "/World")
    stage.Save()
    with pytest.raises(StageError, match=rf"{empty.absolute()}: prim /: the stage holds no UsdGeom.Camera prim"):
        cameras_from_usd(empty, width=32)
    with pytest.raises(StageError, match="no such stage file"):
        cameras_from_usd(tmp_path / "missing.usda", width=32)


def test_cameras_usd_cannot_express(tmp_path: Path) -> None:
    file = tmp_path / "odd.usda"
    stage = new_stage(file)
    UsdGeom.Camera.Define(stage, "/ortho").CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    UsdGeom.Camera.Define(stage, "/squashed").AddScaleOp().Set(Gf.Vec3f(1.0, 2.0, 1.0))
    stage.Save()
    with pytest.raises(StageError, match="prim /ortho: projection is .*only perspective"):
        cameras_from_usd(file, ["/ortho"], width=32)
    with pytest.raises(StageError, match="prim /squashed: .*non-uniform scale"):
        cameras_from_usd(file, ["/squashed"], width=32)
    skewed = Camera(np.array([[100.0, 3.0, 16.0], [0, 100.0, 12.0], [0, 0, 1]]), 32, 24, np.eye(4))
    with pytest.raises(ValueError, match="needs K"):
        camera_to_usd(stage, "/skewed", skewed)
    UsdGeom.Xform.Define(stage, "/thing")
    with pytest.raises(ValueError, match="prim /thing exists and is a Xform"):
        camera_to_usd(stage, "/thing", Camera.from_fov(32, 24, 60.0, np.eye(4)))
    with pytest.raises(ValueError, match="folder .* does not exist"):
        write_cameras_usd(tmp_path / "no" / "cams.usda", [skewed])
