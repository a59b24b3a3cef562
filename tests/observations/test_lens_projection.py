"""Points -> pixels through a frame's lens: training's free-space test, the visibility grid, evaluation.

The lens and its inverse are the test's own (:mod:`tests.captures.test_nerfstudio_distortion`:
OpenCV's formulas written out, fixed-point inversion); the scene is the analytic box of
:mod:`tests.observations.test_visibility`, its depth taken along each pixel's TRUE ray.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from regnf.captures.distortion import Distortion
from regnf.captures.metric import depth_points
from regnf.captures.model import Capture
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.observations.rgbd_samples import backproject_frame, camera_rays
from regnf.observations.view_lenses import ViewLenses
from regnf.observations.visibility import build_visibility
from regnf.render.evaluation import heldout_psnr
from regnf.training.training import _ViewStack
from tests.captures.test_nerfstudio_distortion import forward, inverse
from tests.observations.test_visibility import (
    BOUNDS,
    CAMERAS,
    RES,
    VOXEL,
    H,
    K,
    W,
    box_depth,
    voxel_centres,
)

LENS = {"k1": -0.25, "k2": 0.06, "p1": 1e-3, "p2": -5e-4}
"""OPENCV coefficients of the test camera (monotone at every radius)."""
DISTORTION = Distortion("OPENCV", **LENS)


def project(points: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel ``(u, v)`` and z-depth of world points through the test's own lens, float64."""
    p = (points - c2w[:3, 3]) @ c2w[:3, :3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xd, yd = forward("OPENCV", LENS, p[:, 0] / z, p[:, 1] / z)
    return K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2], z


def distorted_box_capture(root: Path) -> Capture:
    """The box of test_visibility seen by its cameras through :data:`LENS` (depth along the true rays)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    x, y = inverse("OPENCV", LENS, (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1])
    rays = np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3)
    depths = [np.nan_to_num(box_depth(c, rays), posinf=0.0).reshape(H, W) for c in CAMERAS]
    write_capture(root, [np.zeros((H, W, 3), np.uint8)] * len(CAMERAS), depths, np.stack(CAMERAS), K, np.eye(4),
                  meta={"zero_depth": "empty"})
    capture = load_capture(root)
    for frame in capture.frames:
        frame.distortion = DISTORTION
    return capture


def test_pixel_of_goes_through_each_views_lens() -> None:
    # Two views with the same pose: view 0 distorted, view 1 an ideal pinhole.
    c2w = CAMERAS[0]
    Ks = np.stack([K, K])
    w2c = torch.from_numpy(np.linalg.inv(np.stack([c2w, c2w]))).float()
    lenses = ViewLenses.build([DISTORTION, None], Ks, W, H, torch.device("cpu"))
    stack = _ViewStack(torch.zeros(2, H, W), torch.from_numpy(Ks).float(), w2c, lenses)
    rng = np.random.default_rng(0)
    pts = c2w[:3, 3] + (rng.uniform(-1.5, 1.5, (4000, 3)) + [0, 0, 1.6]) @ c2w[:3, :3].T
    x = torch.from_numpy(pts).float()
    u, v, _ = stack.pixel_of(x, torch.zeros(len(pts), dtype=torch.long))
    u, v = u.numpy(), v.numpy()
    tu, tv, tz = project(pts, c2w)
    seen = (tz > 0.1) & (tu >= 0) & (tu < W) & (tv >= 0) & (tv < H)
    assert 1000 < seen.sum() < len(pts) - 1000
    np.testing.assert_allclose(u[seen], tu[seen], atol=2e-3)
    np.testing.assert_allclose(v[seen], tv[seen], atol=2e-3)
    # A point the lens does not image is outside the image (the pinhole pixel may be inside).
    unseen = (tz > 0.1) & ~seen
    assert not ((u[unseen] >= 0) & (u[unseen] < W) & (v[unseen] >= 0) & (v[unseen] < H)).any()
    # The pinhole view: exactly the pinhole arithmetic, in float32 as training does it.
    u1, v1, _ = stack.pixel_of(x, torch.ones(len(pts), dtype=torch.long))
    R, t, Kt = w2c[1, :3, :3], w2c[1, :3, 3], torch.from_numpy(K).float()
    pc = x @ R.T + t
    zs = pc[:, 2].clamp_min(1e-6)
    assert torch.equal(u1, Kt[0, 0] * pc[:, 0] / zs + Kt[0, 2]) and torch.equal(v1, Kt[1, 1] * pc[:, 1] / zs + Kt[1, 2])
    # Far off axis (where the pinhole pixel is far outside): outside the distorted image too.
    far = ((pc[:, 0] / zs).abs() > 5).numpy() & (pc[:, 2] > 0).numpy()
    assert far.any() and (u[far] == -1).all()


def test_the_visibility_grid_of_a_distorted_capture_follows_the_lens(tmp_path: Path) -> None:
    capture = distorted_box_capture(tmp_path / "lens")
    margin = 2.0
    centres = voxel_centres().reshape(-1, 3)
    want = np.zeros(len(centres), np.int64)
    for i, c2w in enumerate(CAMERAS):
        depth = capture.depth(i).astype(np.float64)
        u, v, z = project(centres, c2w)
        inside = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        ui, vi = np.clip(np.nan_to_num(u), 0, W - 1).astype(int), np.clip(np.nan_to_num(v), 0, H - 1).astype(int)
        d = np.where(depth[vi, ui] > 0, depth[vi, ui], np.inf)
        want += inside & (z <= d + margin * VOXEL)
    got = build_visibility(capture, BOUNDS, resolution=RES, margin=margin).counts.numpy().reshape(-1)
    # Only voxel centres within float32 rounding of a pixel edge may differ.
    assert np.mean(got != want) < 2e-3, np.mean(got != want)
    assert want.max() >= 2 and (want == 0).any()
    for frame in capture.frames:
        frame.distortion = None
    pinhole = build_visibility(capture, BOUNDS, resolution=RES, margin=margin).counts.numpy().reshape(-1)
    assert np.mean(pinhole != want) > 0.01  # ignoring the lens is seen


def test_held_out_psnr_refuses_a_distorted_frame(tmp_path: Path) -> None:
    capture = distorted_box_capture(tmp_path / "lens")
    for frame in capture.frames:
        frame.split = "test"
    # Refused before anything is rendered: the field is never used.
    with pytest.raises(ValueError, match=r"meta_data\.json: held-out frame 0 has lens distortion \(OPENCV k1=-0\.25, "
                                         r"k2=0\.06, p1=0\.001, p2=-0\.0005\); held-out PSNR renders pinhole views"):
        heldout_psnr(None, capture)  # type: ignore[arg-type]


def test_without_distortion_rays_points_and_bounds_are_the_pinhole_formulas_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    Ks = np.array([[41.3, 0.2, 23.7], [0.0, 39.1, 18.2], [0.0, 0.0, 1.0]])
    depth = rng.uniform(0.5, 3.0, (36, 48))
    depth[rng.random(depth.shape) < 0.1] = 0.0
    c2w = CAMERAS[1]
    u, v = np.meshgrid(np.arange(48) + 0.5, np.arange(36) + 0.5)
    rays = np.stack([(u - Ks[0, 2]) / Ks[0, 0], (v - Ks[1, 2]) / Ks[1, 1], np.ones_like(u)], -1)
    assert np.array_equal(camera_rays(Ks, 36, 48), rays)
    points, dirs, valid = backproject_frame(depth, Ks, c2w)
    d_world = rays @ c2w[:3, :3].T
    assert np.array_equal(valid, depth > 0)
    assert np.array_equal(points, d_world * depth[..., None] + c2w[:3, 3])
    assert np.array_equal(dirs, d_world / np.linalg.norm(d_world, axis=-1, keepdims=True))
    # The bounds' points (every pixel at this size), skew included.
    y = (v - Ks[1, 2]) / Ks[1, 1]
    x = (u - Ks[0, 2] - Ks[0, 1] * y) / Ks[0, 0]
    keep = depth > 0
    z = depth[keep]
    cam = np.stack([x[keep] * z, y[keep] * z, z], axis=1)
    assert np.array_equal(depth_points(depth, Ks, c2w), cam @ c2w[:3, :3].T + c2w[:3, 3])
