"""Lens distortion against OpenCV's formulas written out here, round trips, numpy/torch, folds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from regnf.captures.distortion import (
    Distortion,
    check_invertible,
    distort,
    distort_within,
    normalised,
    pixels_to_rays,
    undistort,
)

OPENCV = Distortion("OPENCV", k1=-0.28, k2=0.07, p1=1e-3, p2=-5e-4)
"""Realistic radial-tangential coefficients (a phone's or a GoPro's linear mode)."""
FISHEYE = Distortion("OPENCV_FISHEYE", k1=0.05, k2=-0.01, k3=0.002, k4=-0.0005)
"""Realistic equidistant fisheye coefficients."""
W, H = 64, 48
K = np.array([[40.0, 0.0, 31.5], [0.0, 41.0, 24.25], [0.0, 0.0, 1.0]])
"""An image of 64 x 48 pixels, 77 degrees across: corners about 48 degrees off axis."""


def opencv_scalar(x: float, y: float, k1: float, k2: float, k3: float, p1: float, p2: float) -> tuple[float, float]:
    """OpenCV's radial-tangential model, term by term as its documentation writes it."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def fisheye_scalar(x: float, y: float, k1: float, k2: float, k3: float, k4: float) -> tuple[float, float]:
    """OpenCV's equidistant fisheye model, as its documentation writes it."""
    r = math.hypot(x, y)
    if r == 0:
        return x, y
    t = math.atan(r)
    td = t * (1 + k1 * t**2 + k2 * t**4 + k3 * t**6 + k4 * t**8)
    return x * td / r, y * td / r


POINTS = [(0.0, 0.0), (0.3, -0.2), (-0.71, 0.55), (1.1, 0.02), (-0.05, -0.9), (0.8, 0.8)]


def image_points() -> np.ndarray:
    """(H + 1, W + 1, 2) distorted normalised coordinates of every pixel corner, the image's edge included."""
    v, u = np.mgrid[0:H + 1, 0:W + 1].astype(np.float64)
    return normalised(np.stack([u, v], -1), K)


def test_distort_matches_the_formulas_written_out() -> None:
    xy = np.array(POINTS)
    got = distort(xy, OPENCV)
    want = [opencv_scalar(x, y, OPENCV.k1, OPENCV.k2, OPENCV.k3, OPENCV.p1, OPENCV.p2) for x, y in POINTS]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)
    k3 = Distortion("OPENCV", k1=0.1, k2=-0.02, k3=0.004, p1=-2e-3, p2=1e-3)
    want = [opencv_scalar(x, y, k3.k1, k3.k2, k3.k3, k3.p1, k3.p2) for x, y in POINTS]
    np.testing.assert_allclose(distort(xy, k3), want, rtol=0, atol=1e-14)
    want = [fisheye_scalar(x, y, FISHEYE.k1, FISHEYE.k2, FISHEYE.k3, FISHEYE.k4) for x, y in POINTS]
    np.testing.assert_allclose(distort(xy, FISHEYE), want, rtol=0, atol=1e-14)
    # Not the identity: the test would see a model that ignored its coefficients.
    assert np.abs(distort(xy, OPENCV) - xy).max() > 0.1 and np.abs(distort(xy, FISHEYE) - xy).max() > 0.1


@pytest.mark.parametrize("d", [OPENCV, FISHEYE], ids=["opencv", "fisheye"])
def test_undistort_inverts_distort_over_the_image(d: Distortion) -> None:
    # Undistorted points over the whole image (and a little beyond): the round trip x -> x_d -> x.
    xd = image_points()
    x = undistort(xd, d)
    assert np.isfinite(x).all()
    np.testing.assert_allclose(undistort(distort(x * 1.02, d), d), x * 1.02, rtol=0, atol=1e-9)
    np.testing.assert_allclose(distort(x, d), xd, rtol=0, atol=1e-9)
    # The corners move by a lot: far beyond the tolerance.
    assert np.abs(x - xd).max() > 0.05


@pytest.mark.parametrize("d", [OPENCV, FISHEYE], ids=["opencv", "fisheye"])
def test_numpy_and_torch_agree(d: Distortion) -> None:
    xd = image_points()
    t = torch.from_numpy(xd)
    assert isinstance(distort(t, d), torch.Tensor) and isinstance(undistort(t, d), torch.Tensor)
    np.testing.assert_allclose(distort(t, d).numpy(), distort(xd, d), rtol=0, atol=1e-12)
    np.testing.assert_allclose(undistort(t, d).numpy(), undistort(xd, d), rtol=0, atol=1e-12)
    # float32 tensors converge too, to float32's precision.
    x32 = undistort(t.float(), d)
    assert x32.dtype == torch.float32
    np.testing.assert_allclose(x32.double().numpy(), undistort(xd, d), rtol=0, atol=1e-5)


def test_without_distortion_the_rays_are_the_pinhole_ones() -> None:
    zero = Distortion("OPENCV")
    uv = np.array([[0.5, 0.5], [17.25, 30.0], [64.0, 48.0]])
    pinhole = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]], -1)
    np.testing.assert_allclose(pixels_to_rays(uv, K, zero), pinhole, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(distort(pinhole, zero), pinhole)


def test_beyond_the_fold_there_is_no_ray() -> None:
    # r_d = r (1 - 0.4 r^2) peaks at 0.609 (r = 0.913): a distorted radius of 0.7 has no preimage.
    folding = Distortion("OPENCV", k1=-0.4)
    x = undistort(np.array([[0.5, 0.0], [0.7, 0.0], [0.0, -0.65]]), folding)
    assert np.isfinite(x[0]).all() and np.isnan(x[1:]).all()
    np.testing.assert_allclose(distort(x[:1], folding), [[0.5, 0.0]], atol=1e-12)


@pytest.mark.parametrize(("d", "pattern"), [
    (Distortion("OPENCV", k1=-0.4), (r"OPENCV k1=-0\.4: the image \(corners at distorted normalised radius 1\.005\) "
                                     r"is not one-to-one: the lens model folds over 42\.\d degrees off axis")),
    (Distortion("OPENCV", k1=0.3, k2=-0.4), r"OPENCV k1=0\.3, k2=-0\.4: .* folds over"),
    (Distortion("OPENCV_FISHEYE", k1=-0.5), r"OPENCV_FISHEYE k1=-0\.5: .* folds over \d+\.\d degrees off axis"),
])
def test_a_model_that_folds_over_inside_the_image_is_refused(d: Distortion, pattern: str) -> None:
    with pytest.raises(ValueError, match=pattern):
        check_invertible(d, K, W, H)


def test_an_image_wider_than_180_degrees_is_refused() -> None:
    # Equidistant: theta_d = theta < 90 degrees, but the corners are at distorted radius 2.6;
    wide = np.array([[15.0, 0.0, 32.0], [0.0, 15.0, 24.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"OPENCV_FISHEYE k3=1e-09: .* reaches beyond 90 degrees off axis"):
        check_invertible(Distortion("OPENCV_FISHEYE", k3=1e-9), wide, W, H)
    # The same lens on the narrower image is accepted.
    assert check_invertible(Distortion("OPENCV_FISHEYE", k3=1e-9), K, W, H) > 0.985


@pytest.mark.parametrize("d", [OPENCV, FISHEYE], ids=["opencv", "fisheye"])
def test_the_image_lies_within_the_radius_and_beyond_it_nothing_projects(d: Distortion) -> None:
    r_max = check_invertible(d, K, W, H)
    x = undistort(image_points(), d)
    assert np.sqrt((x**2).sum(-1)).max() < r_max
    # Points far off axis (even ones the polynomial would fold back into the image) are outside.
    far = np.array([[r_max * 1.01, 0.0], [0.0, -50.0], [1e30, 1e30], [0.1, 0.2]])
    xy_d, within = distort_within(far, d.model, d.coefficients(), r_max)
    assert within.tolist() == [False, False, False, True]
    assert np.isfinite(xy_d).all()
    np.testing.assert_array_equal(xy_d[3], distort(far[3], d))


def test_coefficients_a_model_does_not_have_are_refused() -> None:
    with pytest.raises(ValueError, match="OPENCV has no k4, got k4=0.1"):
        Distortion("OPENCV", k1=0.1, k4=0.1)
    with pytest.raises(ValueError, match="OPENCV_FISHEYE has no p1, p2"):
        Distortion("OPENCV_FISHEYE", p1=0.1, p2=0.2)
    with pytest.raises(ValueError, match="unknown distortion model 'RADIAL'"):
        Distortion("RADIAL", k1=0.1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        Distortion("OPENCV", k1=math.nan)
