"""Depth normals: central differences of exact depth, windows over noisy depth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from regnf.captures.model import Capture
from regnf.observations.depth_normals import depth_normals, normal_error, window_normals
from regnf.observations.rgbd_samples import backproject_frame

from .capture_helpers import N_VIEWS, box_face_id, pixel_dirs_camera, write_analytic_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Capture:
    return write_analytic_capture(Path(tmp_path_factory.mktemp("analytic_capture")))


# -- central differences ------------------------------------------------------------------------
def test_depth_normals_match_the_analytic_normals_on_flat_faces(capture: Capture) -> None:
    """Away from edges (the pixel and its 4 neighbours on one box face) depth normals are exact."""
    checked = 0
    for i in range(len(capture.frames)):
        frame = capture.frames[i]
        K, c2w = frame.intrinsics, frame.camtoworld
        depth = capture.depth(i).astype(np.float64)
        points, dirs, valid = backproject_frame(depth, K, c2w)
        normals, ok = depth_normals(points, depth, valid, K, dirs)
        face = np.where(valid, box_face_id(points), -1)
        c = face[1:-1, 1:-1]
        flat = np.zeros_like(valid)
        flat[1:-1, 1:-1] = (
            (c >= 0)
            & (face[1:-1, 2:] == c)
            & (face[1:-1, :-2] == c)
            & (face[2:, 1:-1] == c)
            & (face[:-2, 1:-1] == c)
        )
        axis, side = face[flat] // 2, face[flat] % 2
        true_n = np.zeros((int(flat.sum()), 3))
        true_n[np.arange(len(axis)), axis] = np.where(side == 1, 1.0, -1.0)
        # A flat patch is no discontinuity unless seen at grazing incidence (a depth step of
        # 8 pixel footprints is the rule's limit; |cos| > 0.25 keeps it under ~4).
        facing = np.abs((dirs[flat] * true_n).sum(-1)) > 0.25
        assert ok[flat][facing].all(), f"frame {i}: a flat face pixel was rejected"
        trusted = ok[flat]
        cos = (normals[flat][trusted] * true_n[trusted]).sum(-1)
        assert cos.size == 0 or cos.min() > 0.999, f"frame {i}: worst cos {cos.min()}"
        checked += int(trusted.sum())
        # Normals face the camera and are unit length where trusted, zero elsewhere.
        assert ((normals[ok] * dirs[ok]).sum(-1) < 0).all()
        np.testing.assert_allclose(np.linalg.norm(normals[ok], axis=-1), 1.0, atol=1e-9)
        assert (normals[~ok] == 0).all()
    assert checked > 10 * N_VIEWS  # the test must have looked at many face pixels


def test_depth_normals_of_a_slanted_plane_and_a_depth_step() -> None:
    f, h, w = 20.0, 10, 14
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    R = Rotation.from_euler("zyx", [30.0, 10.0, -50.0], degrees=True).as_matrix()
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, [1.0, 2.0, 3.0]
    r = pixel_dirs_camera(K, h, w)

    # A plane tilted 60 degrees from fronto-parallel: steep, but no discontinuity.
    n_cam = np.array([0.0, math.sin(math.radians(60.0)), -math.cos(math.radians(60.0))])
    depth = (n_cam @ np.array([0.0, 0.0, 4.0])) / (r @ n_cam)
    assert (depth > 0).all()
    points, dirs, valid = backproject_frame(depth, K, c2w)
    normals, ok = depth_normals(points, depth, valid, K, dirs)
    assert ok[1:-1, 1:-1].all()
    assert not ok[0].any() and not ok[-1].any() and not ok[:, 0].any() and not ok[:, -1].any()
    np.testing.assert_allclose(
        normals[1:-1, 1:-1], np.broadcast_to(R @ n_cam, (h - 2, w - 2, 3)), atol=1e-9
    )

    # Two fronto-parallel planes, z = 1 (left) and z = 2 (right), and one missing pixel.
    depth = np.where(np.arange(w)[None, :] < w // 2, 1.0, 2.0) * np.ones((h, 1))
    depth[4, 3] = 0.0
    points, dirs, valid = backproject_frame(depth, K, c2w)
    normals, ok = depth_normals(points, depth, valid, K, dirs)
    expect = np.zeros((h, w), bool)
    expect[1:-1, 1:-1] = True
    expect[:, w // 2 - 1 : w // 2 + 1] = False  # either side of the step
    expect[4, 3] = expect[3, 3] = expect[5, 3] = expect[4, 2] = expect[4, 4] = False
    np.testing.assert_array_equal(ok, expect)
    np.testing.assert_allclose(
        normals[ok], np.broadcast_to(R @ [0.0, 0.0, -1.0], (int(ok.sum()), 3)), atol=1e-9
    )


# -- windows over noisy depth -------------------------------------------------------------------
def noisy_plane(sigma: float, seed: int = 0, h: int = 120, w: int = 160, f: float = 100.0):
    """A plane tilted 40 degrees at 2 m with Gaussian z-noise ``sigma``: (points, depth, valid, K, dirs, true normal)."""
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    n_cam = np.array([math.sin(math.radians(40.0)), 0.0, -math.cos(math.radians(40.0))])
    r = pixel_dirs_camera(K, h, w)
    depth = (n_cam @ np.array([0.0, 0.0, 2.0])) / (r @ n_cam)
    depth = depth + np.random.default_rng(seed).normal(0.0, sigma, depth.shape)
    points, dirs, valid = backproject_frame(depth, K, np.eye(4))
    return points, depth, valid, K, dirs, n_cam


def angle_deg(normals: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(normals @ truth, -1.0, 1.0)))


def test_the_predicted_normal_error_matches_the_spread_on_a_noisy_plane() -> None:
    """normal_error's closed form against the angles measured on a plane of known normal."""
    sigma = 0.004  # against a 2.6 cm footprint at 2 m and f = 100 px, seen at 40 degrees
    points, depth, valid, K, dirs, n_true = noisy_plane(sigma)
    for radius in (0, 1, 2, 4):
        normals, ok = window_normals(points, depth, valid, K, dirs, np.full(depth.shape, sigma),
                                     target_deg=0.0, limit_deg=90.0, max_radius=radius)
        # Pixels with the whole window (nearer the border a smaller one is taken).
        inner = np.zeros_like(ok)
        inner[radius + 1 : -radius - 1, radius + 1 : -radius - 1] = True
        assert ok[inner].all()
        err = np.radians(angle_deg(normals[inner], n_true))
        predicted = normal_error(sigma, depth[inner] / K[0, 0], radius)
        # The angle of a 2-D Gaussian tilt: its RMS is sqrt(2) times one axis' sigma; the
        # closed form ignores the incidence, hence the bar of 30 % either way.
        ratio = np.sqrt(np.mean(err**2)) / (math.sqrt(2) * np.mean(predicted))
        assert 0.7 < ratio < 1.3, (radius, ratio)


def test_windows_bring_a_noisy_plane_normal_within_the_target() -> None:
    sigma = 0.02  # about the footprint: central differences are tens of degrees off
    points, depth, valid, K, dirs, n_true = noisy_plane(sigma)
    central, ok0 = depth_normals(points, depth, valid, K, dirs)
    normals, ok = window_normals(points, depth, valid, K, dirs, np.full(depth.shape, sigma))
    assert np.median(angle_deg(central[ok0], n_true)) > 20.0
    assert np.median(angle_deg(normals[ok], n_true)) < 5.0
    # Pixels at least 5 from the border have a whole 9 x 9 window: trusted unless the noise
    # itself made a step of 8 footprints (3.5 sigma) somewhere in the window.
    assert ok[5:-5, 5:-5].mean() > 0.95
    np.testing.assert_allclose(np.linalg.norm(normals[ok], axis=-1), 1.0, atol=1e-9)
    assert ((normals[ok] * dirs[ok]).sum(-1) < 0).all()
    assert (normals[~ok] == 0).all()


def test_exact_depth_keeps_the_central_difference_normals() -> None:
    points, depth, valid, K, dirs, _ = noisy_plane(0.0)
    central, ok0 = depth_normals(points, depth, valid, K, dirs)
    normals, ok = window_normals(points, depth, valid, K, dirs, np.full(depth.shape, 1e-6))
    np.testing.assert_array_equal(ok, ok0)
    np.testing.assert_array_equal(normals, central)


def test_windows_never_reach_across_a_depth_step_or_a_hole() -> None:
    """Two fronto-parallel planes (1 m, 2 m) and a hole, exact depth but a sigma that asks for
    windows: a window across the step would tilt its normal; every trusted one is exact."""
    f, h, w = 100.0, 60, 80
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    depth = np.where(np.arange(w)[None, :] < w // 2, 1.0, 2.0) * np.ones((h, 1))
    depth[30, 20] = 0.0
    points, dirs, valid = backproject_frame(depth, K, np.eye(4))
    sigma = np.full(depth.shape, 0.005)  # half a footprint at 1 m: windows of radius 2
    normals, ok = window_normals(points, depth, valid, K, dirs, sigma)
    _, ok0 = depth_normals(points, depth, valid, K, dirs)
    assert not ok[:, w // 2 - 1 : w // 2 + 1].any()  # either side of the step
    assert not ok[29:32, 19:22].any()  # the hole and its neighbours
    inside = np.zeros_like(ok)
    inside[5:-5, 5:35] = inside[5:-5, 45:75] = True
    inside[26:35, 16:25] = False  # within 2 of the hole's untrusted tangents
    assert ok[inside].all()
    assert ok.sum() > 0.7 * h * w
    np.testing.assert_allclose(normals[ok], np.broadcast_to([0.0, 0.0, -1.0], (int(ok.sum()), 3)), atol=1e-9)
    # A pixel trusted by windows is one whose central-difference tangents were trusted.
    assert not (ok & ~ok0).any()


def test_no_normal_is_trusted_beyond_the_limit() -> None:
    points, depth, valid, K, dirs, _ = noisy_plane(0.0)
    _, ok = window_normals(points, depth, valid, K, dirs, np.full(depth.shape, 10.0))
    assert not ok.any()
