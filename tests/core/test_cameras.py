"""Camera poses, the axis flip and the slab test, against hand-computed geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from regnf.core.cameras import OPENCV_TO_OPENGL, look_at, opencv_to_opengl, pinhole_rays, ray_aabb


def test_look_at_is_opencv() -> None:
    eye, target = np.array([1.0, 2.0, 1.5]), np.array([-1.0, 0.5, 0.3])
    pose = look_at(eye, target)
    R = pose[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R[:, 2], (target - eye) / np.linalg.norm(target - eye))
    np.testing.assert_array_equal(pose[:3, 3], eye)
    assert R[2, 1] < 0  # image y (down) points down in the world
    assert abs(R[2, 0]) < 1e-12  # image x is horizontal
    # Looking along +X with Z up: right is -Y.
    np.testing.assert_allclose(look_at([0, 0, 0], [1, 0, 0])[:3, 0], [0, -1, 0], atol=1e-12)


def test_a_camera_looking_along_up_needs_a_fallback() -> None:
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 2), (0, 0, 0))
    straight_down = look_at([0, 0, 2], [0, 0, 0], fallback_up=(1.0, 0.0, 0.0))
    np.testing.assert_allclose(straight_down[:3, 2], [0, 0, -1])
    # Image up (-y) is the fallback's direction: image y is -X.
    np.testing.assert_allclose(straight_down[:3, 1], [-1, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="coincide"):
        look_at([1, 1, 1], [1, 1, 1])


def test_the_flip_turns_opencv_into_opengl_and_back() -> None:
    pose = look_at([1.0, -2.0, 1.5], [0.0, 0.0, 0.5])
    gl = opencv_to_opengl(pose)
    # OpenGL looks along -z with y up: the same viewing direction and the same centre.
    np.testing.assert_allclose(-gl[:3, 2], pose[:3, 2])
    np.testing.assert_allclose(gl[:3, 1], -pose[:3, 1])
    np.testing.assert_array_equal(gl[:3, 3], pose[:3, 3])
    np.testing.assert_array_equal(opencv_to_opengl(gl), pose)
    np.testing.assert_array_equal(OPENCV_TO_OPENGL @ OPENCV_TO_OPENGL, np.eye(4))


def test_ray_aabb_axis_parallel() -> None:
    o = torch.tensor([[0.0, 0.0, -2.0], [2.0, 0.0, -2.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t_in, t_out = ray_aabb(o, d, torch.tensor([-1.0] * 3), torch.tensor([1.0] * 3))
    assert t_in.tolist()[0] == 1.0 and t_out.tolist()[0] == 3.0
    assert bool(t_in[1] > t_out[1])
    assert not bool(torch.isnan(t_in).any() | torch.isnan(t_out).any())


def test_ray_aabb_diagonal_hand_computed() -> None:
    # From (-2, -2, 0.5) along (1, 1, 0)/sqrt(2) into [-1, 1]^3: enters at x = y = -1.
    s2 = np.sqrt(2.0)
    o = torch.tensor([[-2.0, -2.0, 0.5]], dtype=torch.float64)
    d = torch.tensor([[1 / s2, 1 / s2, 0.0]], dtype=torch.float64)
    t_in, t_out = ray_aabb(o, d, -torch.ones(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64))
    assert t_in.item() == pytest.approx(s2) and t_out.item() == pytest.approx(3 * s2)


def test_pinhole_rays_pass_through_pixel_centres() -> None:
    K = np.array([[100.0, 0.0, 32.0], [0.0, 120.0, 24.0], [0.0, 0.0, 1.0]])
    C = look_at(np.array([1.0, -2.0, 0.5]), np.array([0.0, 0.3, 0.1]))
    o, d, z = pinhole_rays(K, C, 64, 48, device="cpu", dtype=torch.float64)
    assert o.shape == (64 * 48, 3) and d.shape == (64 * 48, 3) and z.shape == (64 * 48,)
    assert o.device == torch.device("cpu")
    # Pixel (u=5, v=7) by hand: centre (5.5, 7.5), row-major index 7 * 64 + 5.
    d_cam = np.array([(5.5 - 32.0) / 100.0, (7.5 - 24.0) / 120.0, 1.0])
    d_cam /= np.linalg.norm(d_cam)
    i = 7 * 64 + 5
    np.testing.assert_allclose(d[i].numpy(), C[:3, :3] @ d_cam, atol=1e-12)
    np.testing.assert_allclose(o[i].numpy(), C[:3, 3], atol=1e-12)
    np.testing.assert_allclose(float(z[i]), d_cam[2], atol=1e-12)
    np.testing.assert_allclose(torch.linalg.vector_norm(d, dim=-1).numpy(), 1.0, atol=1e-12)
    # Stride: every 4th pixel, still through the kept pixels' centres.
    _, d4, _ = pinhole_rays(K, C, 64, 48, stride=4, dtype=torch.float64)
    assert d4.shape == (16 * 12, 3)
    np.testing.assert_allclose(d4[1].numpy(), d[4].numpy(), atol=1e-12)
    np.testing.assert_allclose(d4[16].numpy(), d[4 * 64].numpy(), atol=1e-12)
    assert pinhole_rays(K, C, 64, 48)[0].dtype == torch.float32
    with pytest.raises(ValueError, match="stride"):
        pinhole_rays(K, C, 64, 48, stride=0)
    with pytest.raises(ValueError, match="K"):
        pinhole_rays(np.zeros((3, 3)), C, 64, 48)
    with pytest.raises(ValueError, match="width"):
        pinhole_rays(K, C, 0, 48)
    with pytest.raises(ValueError, match="camtoworld"):
        pinhole_rays(K, np.eye(3), 64, 48)
