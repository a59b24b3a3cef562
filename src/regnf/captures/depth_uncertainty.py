"""How uncertain a sensor's depth is, per pixel: the model training weights its depth terms by.

A structured-light or stereo sensor's depth error grows with the square of the distance and
with the angle at which the surface is seen. :class:`DepthNoiseModel` is the axial model of
Nguyen, Izadi and Lovell 2012 ("Modeling Kinect Sensor Noise for Improved 3D Reconstruction
and Tracking")::

    sigma_z(z, theta) = a + b (z - z0)^2 + c / sqrt(z) * theta^2 / (pi/2 - theta)^2   metres

with z the z-depth in metres and theta the angle between the ray and the surface normal, and
the lateral noise ``lateral_px``: how far from its pixel's centre a depth may have been read
(ICL-NUIM's half a pixel by default), which decides how near an outline free space reaches. Its
axial defaults are their Kinect constants; the synthetic sensor (:mod:`regnf.synthetic.sensor_noise`)
draws its axial noise from the same closed form (:func:`axial_sigma`), so the captures regnf
makes noisy and the trainer that reads them agree on the model.

A capture says which model its depth follows (:attr:`regnf.captures.model.Capture.depth_noise`):
none for regnf's own ideal renders (exact depth), this model for every other capture, or the
model its metadata names (``regnf.depth_noise``, :func:`parse_depth_noise`). Training weights a
sample by ``(reference_m / sigma)^2`` clipped to ``[min_weight, 1]``
(:meth:`DepthNoiseModel.weight`; docs/decisions/depth-weights.md says why these values).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from regnf.core.errors import RegnfError

ArrayT = TypeVar("ArrayT", bound=Any)
"""A numpy array or a torch tensor (or a float)."""

MAX_THETA = math.radians(89.9)
"""Largest incidence angle the closed forms are evaluated at, radians (they diverge at 90)."""

CONFIDENCE_WEIGHTS = (0.0, 0.5, 1.0)
"""Weight factor of ARKit's depth confidence 0 (low), 1 (medium), 2 (high); 0: the depth is unknown."""

DEPTH_NOISE_KEY = "depth_noise"
"""Key of the ``regnf`` metadata block naming a capture's depth noise model (``"none"`` or an object)."""


@dataclass(frozen=True)
class DepthNoiseModel:
    """Axial depth noise ``sigma_z(z, theta)`` of a sensor and the sample weights it gives."""

    constant_m: float = 0.0012
    """Constant term a of sigma_z, metres."""
    quadratic_per_m: float = 0.0019
    """Coefficient b of (z - z0)^2, 1/metres."""
    quadratic_origin_m: float = 0.4
    """Depth z0 at which the quadratic term vanishes, metres."""
    angular_m15: float = 0.0001
    """Coefficient c of theta^2 / (pi/2 - theta)^2 / sqrt(z), metres^1.5."""
    reference_m: float = 0.002
    """Sigma of weight 1: a sample whose sigma is this or less counts fully, metres."""
    min_weight: float = 0.1
    """Smallest weight of a sample however noisy its depth (a fraction, in (0, 1])."""
    lateral_px: float = 0.5
    """Lateral noise: sigma of the offset of the point a pixel's depth is read at, pixels of the capture's depth images."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise RegnfError(f"{f.name} must be a finite number, got {value!r}")
        if self.constant_m <= 0 or self.quadratic_per_m < 0 or self.angular_m15 < 0:
            raise RegnfError(
                "constant_m must be > 0 and quadratic_per_m, angular_m15 >= 0 (sigma must be "
                f"positive), got {self.constant_m:g}, {self.quadratic_per_m:g}, {self.angular_m15:g}"
            )
        if self.quadratic_origin_m < 0 or self.reference_m <= 0:
            raise RegnfError(
                f"quadratic_origin_m must be >= 0 and reference_m > 0, got "
                f"{self.quadratic_origin_m:g}, {self.reference_m:g}"
            )
        if not 0 < self.min_weight <= 1:
            raise RegnfError(f"min_weight must be in (0, 1], got {self.min_weight:g}")
        if self.lateral_px < 0:
            raise RegnfError(f"lateral_px must be >= 0, got {self.lateral_px:g}")

    def sigma_normal(self, z: ArrayT) -> ArrayT:
        """``a + b (z - z0)^2``: sigma at normal incidence, metres, of z-depth ``z`` (metres, > 0).

        Plain arithmetic, so that it takes numpy arrays and torch tensors alike.
        """
        return self.constant_m + self.quadratic_per_m * (z - self.quadratic_origin_m) ** 2

    def sigma(self, z: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Axial depth noise sigma_z(z, theta), metres.

        Parameters
        ----------
        z : (...) float
            z-depth, metres (clamped to 1e-6 from below).
        theta : (...) float
            Angle between the ray and the surface normal, radians (clamped to :data:`MAX_THETA`).

        Returns
        -------
        (...) float64
        """
        z = np.maximum(np.asarray(z, dtype=np.float64), 1e-6)
        theta = np.minimum(np.asarray(theta, dtype=np.float64), MAX_THETA)
        angular = self.angular_m15 / np.sqrt(z) * theta**2 / (np.pi / 2 - theta) ** 2
        return self.sigma_normal(z) + angular

    def scaled(self, factor: float) -> DepthNoiseModel:
        """The model with sigma multiplied by ``factor`` (> 0): its three terms scaled, its weights' constants kept."""
        return dataclasses.replace(self, constant_m=self.constant_m * factor, quadratic_per_m=self.quadratic_per_m * factor,
                                   angular_m15=self.angular_m15 * factor)

    def weight(self, sigma: np.ndarray) -> np.ndarray:
        """(...) float64: ``(reference_m / sigma)^2`` clipped to ``[min_weight, 1]`` (sigma in metres)."""
        return np.clip((self.reference_m / np.asarray(sigma, dtype=np.float64)) ** 2, self.min_weight, 1.0)


def axial_sigma(z: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Nguyen et al.'s axial depth noise with their Kinect constants (:class:`DepthNoiseModel`'s defaults), metres.

    Parameters
    ----------
    z : (...) float
        Depth, metres.
    theta : (...) float
        Angle between the ray and the surface normal, radians (clamped to :data:`MAX_THETA`).

    Returns
    -------
    (...) float64
    """
    return DepthNoiseModel().sigma(z, theta)


def parse_depth_noise(value: object) -> DepthNoiseModel | None:
    """The model a capture's ``regnf.depth_noise`` names: ``"none"`` (exact depth) or an object.

    The object holds any of :class:`DepthNoiseModel`'s fields (the others keep their defaults).
    The message of a refusal names the key, not the file: the caller adds where.

    Raises
    ------
    ValueError
        Another string, an unknown field, or a value the model refuses.
    """
    where = f"regnf.{DEPTH_NOISE_KEY}"
    if value == "none":
        return None
    if not isinstance(value, dict):
        # Bad metadata, not a bad argument: the capture's error type, a ValueError.
        raise RegnfError(f"{where} must be 'none' or an object of model fields, got {value!r}")
    names = [f.name for f in dataclasses.fields(DepthNoiseModel)]
    unknown = sorted(set(value) - set(names))
    if unknown:
        raise RegnfError(f"{where} has unknown field(s) {', '.join(map(repr, unknown))}; known: {', '.join(names)}")
    try:
        return DepthNoiseModel(**value)
    except ValueError as exc:
        raise RegnfError(f"{where}: {exc}") from exc
