"""Cameras from a capture's trajectory and orbits around a scene's bounds."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from regnf.captures.model import Capture, CaptureError
from regnf.compositor import Camera, render
from regnf.compositor.cameras_io import (
    OrbitConfig,
    cameras_from_capture,
    field_bounds_metres,
    orbit_around_bounds,
    resized,
)
from regnf.fields.analytic import Box, Union
from tests.observations import capture_helpers as C

from .golden_scenes import sim


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Capture:
    return C.write_analytic_capture(tmp_path_factory.mktemp("cap") / "capture")


def test_capture_cameras_see_what_the_capture_saw(capture: Capture) -> None:
    """The captured analytic object, placed in metres by the capture's worldtogt, renders from
    the loaded cameras as the capture recorded it: same silhouette, same depth in metres."""
    obj = C.analytic_object()
    field = Union(*obj.fields, to_world=C.WORLDTOGT)
    frames = [1, 5, 22]
    cams = cameras_from_capture(capture.root, indices=frames)
    assert len(cams) == 3 and all((c.width, c.height) == (C.WIDTH, C.HEIGHT) for c in cams)
    for i, cam in zip(frames, cams, strict=True):
        np.testing.assert_allclose(cam.camera_to_world, capture.camtoworld_metres(i), atol=1e-12)
        r = render(field, cam)
        seen = capture.depth(i) * capture.scale  # metres
        mask = r.mask.numpy()
        assert np.mean(mask == (seen > 0)) > 0.995
        both = mask & (seen > 0)
        assert np.median(np.abs(r.depth.numpy()[both] - seen[both])) < 1e-3


def test_resizing_scales_the_intrinsics(capture: Capture) -> None:
    (cam,) = cameras_from_capture(capture.root, width=32, indices=[3])
    assert (cam.width, cam.height) == (32, 32)  # the other side follows the aspect ratio
    np.testing.assert_allclose(cam.K, np.diag([0.5, 0.5, 1.0]) @ C.K)
    # Pixel (u, v) of the half-size image looks through the corner shared by original pixels
    # (2u, 2v) .. (2u + 1, 2v + 1), i.e. original coordinate (2u + 1, 2v + 1).
    u, v = 7, 11
    small = np.linalg.solve(cam.K, [u + 0.5, v + 0.5, 1.0])
    full = np.linalg.solve(C.K, [2 * u + 1.0, 2 * v + 1.0, 1.0])
    np.testing.assert_allclose(small, full, atol=1e-12)
    wide = resized(Camera(C.K, 64, 64, np.eye(4)), 128, 32)
    np.testing.assert_allclose(wide.K, np.diag([2.0, 0.5, 1.0]) @ C.K)


def test_capture_errors_name_the_problem(capture: Capture, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="out of range"):
        cameras_from_capture(capture.root, indices=[40])
    with pytest.raises(CaptureError, match="meta_data.json"):
        cameras_from_capture(tmp_path / "nothing")


def test_orbit_circles_the_target_and_looks_at_it() -> None:
    bounds = np.array([[-3.0, -2.5, 0.0], [3.0, 2.5, 2.5]])
    cfg = OrbitConfig(n=6, width=40, height=30, elevation_deg=30.0)
    cams = orbit_around_bounds(bounds, cfg)
    target = np.array([0.0, 0.0, 0.5])  # centre, 20 % up the box
    radius = 0.4 * 5.0  # of the smaller horizontal side
    assert len(cams) == 6
    for k, cam in enumerate(cams):
        offset = cam.center - target
        assert math.hypot(offset[0], offset[1]) == pytest.approx(radius)
        assert math.degrees(math.atan2(offset[2], radius)) == pytest.approx(30.0)
        assert math.atan2(offset[1], offset[0]) % (2 * math.pi) == pytest.approx(2 * math.pi * k / 6, abs=1e-12)
        forward = cam.camera_to_world[:3, 2]
        np.testing.assert_allclose(forward, -offset / np.linalg.norm(offset), atol=1e-12)
        assert cam.camera_to_world[2, 1] < 0  # image down is world down-ish: upright views
    fixed = orbit_around_bounds(bounds, OrbitConfig(n=1, radius=1.0))
    assert np.linalg.norm(fixed[0].center[:2]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="max > min"):
        orbit_around_bounds(np.zeros((2, 3)))


def test_field_bounds_in_metres() -> None:
    box = Box((1.0, 0.5, 0.25), to_world=sim(90.0, (1.0, 2.0, 3.0), 2.0))
    lo, hi = field_bounds_metres(box)
    pad = 0.02 * 2.0  # analytic bounds are padded by 2 % of the largest extent
    np.testing.assert_allclose(lo, [1.0 - 2 * (0.5 + pad), 2.0 - 2 * (1.0 + pad), 3.0 - 2 * (0.25 + pad)], atol=1e-6)
    np.testing.assert_allclose(hi, [1.0 + 2 * (0.5 + pad), 2.0 + 2 * (1.0 + pad), 3.0 + 2 * (0.25 + pad)], atol=1e-6)

