"""Lens distortion of a capture's cameras: the OpenCV and OpenCV-fisheye models.

A frame with a :class:`Distortion` sees along rays that a pinhole ``K`` alone does not give:
pixel -> ray goes through ``K^-1`` and then :func:`undistort`; point -> pixel goes through
:func:`distort` and then ``K``. Coordinates in between are normalised image coordinates
``(x / z, y / z)`` of the OpenCV camera frame (x right, y down, z forward).

The functions take numpy arrays or torch tensors (one implementation: the few math functions
are taken from the input's library) and broadcast over leading axes. :func:`undistort` is
Newton's method with the analytic 2x2 Jacobian; where it does not converge, or converges onto
the far side of a fold, there is no ray and it returns NaN. :func:`check_invertible` refuses a
model that folds over inside the image, and gives the radius beyond which a projected point is
outside the image whatever the polynomial says (beyond it the polynomial may fold back in).
See ``docs/decisions/lens-distortion.md`` for the numeric choices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import astuple, dataclass
from typing import Any, Literal

import numpy as np

from regnf.core.errors import RegnfError


@dataclass(frozen=True)
class Distortion:
    """The distortion coefficients of one camera (nerfstudio's and OpenCV's names)."""

    model: Literal["OPENCV", "OPENCV_FISHEYE"]
    """OPENCV: radial k1, k2, k3 and tangential p1, p2; OPENCV_FISHEYE: equidistant k1..k4."""
    k1: float = 0.0
    """First radial coefficient."""
    k2: float = 0.0
    """Second radial coefficient."""
    k3: float = 0.0
    """Third radial coefficient."""
    k4: float = 0.0
    """Fourth radial coefficient (OPENCV_FISHEYE only)."""
    p1: float = 0.0
    """First tangential coefficient (OPENCV only)."""
    p2: float = 0.0
    """Second tangential coefficient (OPENCV only)."""

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise RegnfError(f"unknown distortion model {self.model!r}; known: {', '.join(MODELS)}")
        values = astuple(self)[1:]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise RegnfError(f"distortion coefficients must be finite numbers, got {values}")
        # A coefficient the model does not use would be silently ignored: refuse it.
        unused = ("k4",) if self.model == "OPENCV" else ("p1", "p2")
        bad = [k for k in unused if getattr(self, k) != 0.0]
        if bad:
            got = ", ".join(f"{k}={getattr(self, k):g}" for k in bad)
            raise RegnfError(f"{self.model} has no {', '.join(bad)}, got {got}")

    def coefficients(self) -> tuple[float, float, float, float, float, float]:
        """``(k1, k2, k3, k4, p1, p2)``, the order :func:`distort_per_point` takes."""
        return (self.k1, self.k2, self.k3, self.k4, self.p1, self.p2)

    def describe(self) -> str:
        """The model and its non-zero coefficients, e.g. ``OPENCV k1=-0.28, p2=0.001``."""
        names = ("k1", "k2", "k3", "k4", "p1", "p2")
        nonzero = [f"{k}={v:g}" for k, v in zip(names, self.coefficients()) if v != 0.0]
        return f"{self.model} {', '.join(nonzero) or 'without coefficients'}"


MODELS = ("OPENCV", "OPENCV_FISHEYE")
"""Distortion models: OpenCV's radial-tangential one and its equidistant fisheye one."""

NEWTON_STEPS = 20
"""Newton iterations of :func:`undistort` (from a start that is exact without distortion)."""

TOLERANCE_EPS = 64.0
"""Largest residual ``|distort(x) - x_d|`` of a converged :func:`undistort`, in machine epsilons
of the input's dtype times ``max(1, |x_d|)``."""

FOLD_ANGLES = 2048
"""Off-axis angles (0 to 90 degrees, evenly spaced) at which :func:`check_invertible` tests the map."""

FOLD_DIRECTIONS = 64
"""Directions around the optical axis at which :func:`check_invertible` tests the map."""

Array = Any
"""A numpy array or a torch tensor (the functions return the type they are given)."""


def _lib(x: Array) -> Any:
    """numpy for a numpy array, torch for a tensor: both spell the few functions used alike."""
    if isinstance(x, np.ndarray):
        return np
    import torch  # only a tensor's caller has torch loaded; the captures package needs no torch

    return torch


def _forward(x: Array, y: Array, model: str, c: Sequence[Any], xp: Any) -> tuple[Array, Array]:
    """Distorted ``(x_d, y_d)`` of undistorted ``(x, y)``; ``c`` = (k1, k2, k3, k4, p1, p2)."""
    k1, k2, k3, k4, p1, p2 = c
    r2 = x * x + y * y
    if model == "OPENCV":
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
    r = xp.sqrt(r2)
    theta = xp.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    pos = r > 0
    scale = xp.where(pos, theta_d / xp.where(pos, r, 1.0), 1.0)
    return x * scale, y * scale


def _jacobian(x: Array, y: Array, model: str, c: Sequence[Any], xp: Any) -> tuple[Array, Array, Array, Array]:
    """``d(x_d, y_d) / d(x, y)`` as ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)``."""
    k1, k2, k3, k4, p1, p2 = c
    r2 = x * x + y * y
    if model == "OPENCV":
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        off = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        return (radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x, off,
                off, radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x)
    # x_d = s(r) x with s = theta_d / r: J = s I + (s'(r) / r) [x, y]^T [x, y].
    r = xp.sqrt(r2)
    theta = xp.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    d_theta_d = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    pos = r > 0
    rs = xp.where(pos, r, 1.0)
    s = xp.where(pos, theta_d / rs, 1.0)
    g = xp.where(pos, (d_theta_d / (1.0 + r2) - s) / (rs * rs), 0.0)
    return s + g * x * x, g * x * y, g * x * y, s + g * y * y


def distort_per_point(xy: Array, model: str, coeffs: Sequence[Any]) -> Array:
    """:func:`distort` with coefficients that may differ per point.

    Parameters
    ----------
    xy : (..., 2) float array or tensor
        Undistorted normalised image coordinates.
    model : str
        One of :data:`MODELS` (for every point).
    coeffs : six floats or (...,) arrays / tensors
        ``(k1, k2, k3, k4, p1, p2)``, each broadcast against ``xy[..., 0]``.

    Returns
    -------
    (..., 2), the type and dtype of ``xy``
        Distorted normalised image coordinates.
    """
    xp = _lib(xy)
    xd, yd = _forward(xy[..., 0], xy[..., 1], model, coeffs, xp)
    return xp.stack([xd, yd], -1)


def distort(xy: Array, d: Distortion) -> Array:
    """Distorted normalised coordinates (..., 2) of undistorted ones ``xy`` (..., 2).

    OPENCV: ``r2 = x^2 + y^2``, ``radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3``,
    ``x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)``, ``y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y``.
    OPENCV_FISHEYE: ``theta = atan(r)``, ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``,
    ``xy_d = xy theta_d / r`` (``xy`` at ``r = 0``). Numpy in, numpy out; torch in, torch out.
    """
    return distort_per_point(xy, d.model, d.coefficients())


def undistort(xy_d: Array, d: Distortion) -> Array:
    """Undistorted normalised coordinates (..., 2) of distorted ones ``xy_d``; NaN where none.

    :data:`NEWTON_STEPS` Newton steps with the analytic Jacobian, vectorised, from the point
    itself (OPENCV) or from the pinhole angle ``tan(|xy_d|)`` (fisheye). A point is kept where
    the residual is within :data:`TOLERANCE_EPS` and the Jacobian's determinant is positive
    there (not on the far side of a fold); elsewhere the model is not invertible and the result
    is NaN: the pixel has no ray.
    """
    xp = _lib(xy_d)
    c = d.coefficients()
    xd, yd = xy_d[..., 0], xy_d[..., 1]
    if d.model == "OPENCV":
        x, y = xd, yd
    else:
        rho = xp.sqrt(xd * xd + yd * yd)
        pos = rho > 0
        # Without distortion theta_d = theta: start there (capped short of 90 degrees).
        start = xp.where(pos, xp.tan(xp.where(rho < 1.5, rho, 1.5)) / xp.where(pos, rho, 1.0), 1.0)
        x, y = xd * start, yd * start
    with np.errstate(all="ignore"):  # diverging points overflow; they are NaN below
        for _ in range(NEWTON_STEPS):
            fx, fy = _forward(x, y, d.model, c, xp)
            fx, fy = fx - xd, fy - yd
            a, b, cc, dd = _jacobian(x, y, d.model, c, xp)
            det = a * dd - b * cc
            x, y = x - (dd * fx - b * fy) / det, y - (a * fy - cc * fx) / det
        fx, fy = _forward(x, y, d.model, c, xp)
        a, b, cc, dd = _jacobian(x, y, d.model, c, xp)
        size = xp.sqrt(xd * xd + yd * yd)
        tol = TOLERANCE_EPS * xp.finfo(xy_d.dtype).eps * xp.where(size > 1.0, size, 1.0)
        ok = (xp.abs(fx - xd) <= tol) & (xp.abs(fy - yd) <= tol) & (a * dd - b * cc > 0)
    return xp.stack([xp.where(ok, x, float("nan")), xp.where(ok, y, float("nan"))], -1)


def distort_within(xy: Array, model: str, coeffs: Sequence[Any], r_max: Any) -> tuple[Array, Array]:
    """Distort the points within the radius :func:`check_invertible` gives; flag the others.

    Parameters
    ----------
    xy : (..., 2) float array or tensor
        Undistorted normalised coordinates (any size: a point far off axis is flagged).
    model, coeffs
        As :func:`distort_per_point`.
    r_max : float or (...,) array / tensor
        :func:`check_invertible`'s radius (``inf`` for a camera without distortion).

    Returns
    -------
    xy_d : (..., 2)
        Distorted coordinates; 0 where not within.
    within : (...,) bool
        ``|xy| <= r_max``: only there does the lens image the point at ``xy_d`` (beyond, the
        polynomial may fold back into the image), and only there is ``xy_d`` meaningful.
    """
    xp = _lib(xy)
    with np.errstate(all="ignore"):
        r2 = xy[..., 0] * xy[..., 0] + xy[..., 1] * xy[..., 1]
        within = r2 <= r_max * r_max
    # Zero the others before the polynomial: a huge radius overflows, and 0 * inf is NaN.
    safe = xp.where(within[..., None], xy, 0.0)
    return distort_per_point(safe, model, coeffs), within


def normalised(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 2) float64 ``K^-1 (u, v, 1)`` (distorted normalised coordinates), skew included."""
    K = np.asarray(K, dtype=np.float64)
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y], -1)


def pixels_to_rays(uv: np.ndarray, K: np.ndarray, d: Distortion) -> np.ndarray:
    """(..., 2) float64 undistorted ``(x, y)`` of pixel positions ``uv`` (ray ``(x, y, 1)``); NaN: no ray."""
    return undistort(normalised(np.asarray(uv, dtype=np.float64), K), d)


def _image_border(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n, 2) distorted normalised coordinates of the image's outline, one point per pixel edge."""
    u = np.arange(width + 1, dtype=np.float64)
    v = np.arange(height + 1, dtype=np.float64)
    uv = np.concatenate([
        np.stack([u, np.zeros_like(u)], -1), np.stack([u, np.full_like(u, height)], -1),
        np.stack([np.zeros_like(v), v], -1), np.stack([np.full_like(v, width), v], -1),
    ])
    return normalised(uv, K)


def image_outline_rays(d: Distortion | None, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n, 3) float64 camera rays ``(x, y, 1)`` through the image's outline (one per pixel edge).

    The undistorted outline bounds every ray of the image (the map keeps its inside inside);
    without distortion it is a rectangle and its 4 corners suffice, but a distorted one bulges.
    Points without a ray are left out.
    """
    xy = _image_border(K, width, height)
    if d is not None:
        xy = undistort(xy, d)
        xy = xy[np.isfinite(xy).all(-1)]
    return np.concatenate([xy, np.ones((len(xy), 1))], -1)


def check_invertible(d: Distortion, K: np.ndarray, width: int, height: int) -> float:
    """Refuse a model that folds over inside the image; return the radius that holds the image.

    The map is sampled at :data:`FOLD_ANGLES` off-axis angles (undistorted radius
    ``tan(angle)``) times :data:`FOLD_DIRECTIONS` directions. It must keep a positive Jacobian
    determinant out to a radius ``r_max`` at which every direction already lands beyond the
    image's farthest corner (in distorted normalised coordinates); the image's outline must
    then undistort (:func:`undistort` converges there).

    Parameters
    ----------
    d : Distortion
    K : (3, 3) float
        Pinhole intrinsics of the image; pixel centres at ``(u + 0.5, v + 0.5)``.
    width, height : int
        Image size, pixels.

    Returns
    -------
    float
        ``r_max``, undistorted normalised radius: a point beyond it is outside the image
        (:func:`distort_within`), within it the map is one-to-one.

    Raises
    ------
    ValueError
        One line naming the coefficients and the off-axis angle where the map folds, or that
        the image reaches beyond 90 degrees off axis.
    """
    rho = float(np.sqrt((normalised(np.array([[0.0, 0.0], [width, 0.0], [0.0, height],
                                               [width, height]]), K) ** 2).sum(-1)).max())
    angle = np.linspace(0.0, 0.5 * np.pi, FOLD_ANGLES + 1)[:-1]
    turn = np.linspace(0.0, 2.0 * np.pi, FOLD_DIRECTIONS, endpoint=False)
    r = np.tan(angle)[:, None]
    x, y = r * np.cos(turn), r * np.sin(turn)
    c = d.coefficients()
    with np.errstate(all="ignore"):
        xd, yd = _forward(x, y, d.model, c, np)
        a, b, cc, dd = _jacobian(x, y, d.model, c, np)
        folded = ~(a * dd - b * cc > 0).all(-1)
        covers = np.sqrt(xd * xd + yd * yd).min(-1) > rho
    first_fold = int(np.argmax(folded)) if folded.any() else len(angle)
    first_cover = int(np.argmax(covers)) if covers.any() else len(angle)
    where = f"{d.describe()}: the image (corners at distorted normalised radius {rho:.4g})"
    if first_fold <= first_cover:
        if first_fold == len(angle):
            raise RegnfError(f"{where} reaches beyond 90 degrees off axis, which a pinhole ray cannot represent")
        raise RegnfError(
            f"{where} is not one-to-one: the lens model folds over {np.degrees(angle[first_fold]):.1f} degrees "
            f"off axis (normalised radius {float(r[first_fold, 0]):.4g}), inside the image"
        )
    outline = undistort(_image_border(K, width, height), d)
    if not np.isfinite(outline).all():
        raise RegnfError(f"{where} does not invert at the image's outline")
    return float(r[first_cover, 0])
