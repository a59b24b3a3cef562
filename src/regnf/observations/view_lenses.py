"""The lens distortion of a stack of training views, for projecting points into them on the device.

A capture's frames may each have a :class:`~regnf.captures.distortion.Distortion` (or none).
:class:`ViewLenses` holds their coefficients per view so that a batch of points, each projected
into its own view, is distorted in one vectorised pass per distortion model
(:func:`~regnf.captures.distortion.distort_within`); a point beyond the radius that holds the
view's image (:func:`~regnf.captures.distortion.check_invertible`) is outside it.
:class:`FrameLens` does the same for one view and many points (the visibility grid's voxels).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from regnf.captures.distortion import MODELS, Distortion, check_invertible, distort_within


class ViewLenses:
    """Per-view distortion coefficients, models and image radii (on one device)."""

    def __init__(self, coeffs: torch.Tensor, model_of: dict[str, torch.Tensor], r_max: torch.Tensor,
                 distorted: torch.Tensor) -> None:
        self.coeffs = coeffs
        """(V, 6) ``(k1, k2, k3, k4, p1, p2)`` per view (0 for a view without distortion)."""
        self.model_of = model_of
        """Per distortion model present, (V,) bool: the views of that model."""
        self.r_max = r_max
        """(V,) undistorted normalised radius holding each view's image (``inf`` without distortion)."""
        self.distorted = distorted
        """(V,) bool: the view has a distortion."""

    @staticmethod
    def build(distortions: Sequence[Distortion | None], K: np.ndarray, width: int, height: int,
              device: torch.device) -> ViewLenses | None:
        """The lenses of views with ``distortions`` and intrinsics ``K`` (V, 3, 3); None if none is distorted.

        Raises
        ------
        ValueError
            A distortion that :func:`~regnf.captures.distortion.check_invertible` refuses.
        """
        if all(d is None for d in distortions):
            return None
        n = len(distortions)
        coeffs = np.zeros((n, 6))
        r_max = np.full(n, np.inf)
        radius: dict[tuple, float] = {}
        for i, d in enumerate(distortions):  # a loop over views, each checked once per camera
            if d is None:
                continue
            coeffs[i] = d.coefficients()
            key = (d, tuple(np.asarray(K[i], dtype=np.float64).ravel().tolist()))
            if key not in radius:
                radius[key] = check_invertible(d, K[i], width, height)
            r_max[i] = radius[key]
        model_of = {
            m: torch.tensor([d is not None and d.model == m for d in distortions], device=device)
            for m in MODELS if any(d is not None and d.model == m for d in distortions)
        }
        distorted = torch.tensor([d is not None for d in distortions], device=device)
        return ViewLenses(torch.from_numpy(coeffs).float().to(device), model_of,
                          torch.from_numpy(r_max).float().to(device), distorted)

    def pixels(self, xy: torch.Tensor, view: torch.Tensor,
               K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel coordinates of undistorted normalised points ``xy`` (n, 2) in views ``view`` (n,).

        Parameters
        ----------
        xy : (n, 2) float
            ``(x / z, y / z)`` in each point's view.
        view : (n,) long
            The view of each point.
        K : (n, 3, 3) float
            Each point's view's intrinsics.

        Returns
        -------
        u, v : (n,) float
            Pixel coordinates through the lens (skew included); ``-1`` (outside every image)
            where the point lies beyond the view's :attr:`r_max`.
        distorted : (n,) bool
            The point's view has a distortion (elsewhere ``u, v`` are meaningless).
        """
        coeffs = self.coeffs[view].unbind(-1)
        r_max = self.r_max[view]
        xy_d = torch.zeros_like(xy)
        within = torch.zeros(xy.shape[:-1], dtype=torch.bool, device=xy.device)
        for model, of_model in self.model_of.items():  # at most the two models
            sel = of_model[view]
            xy_m, within_m = distort_within(xy, model, coeffs, r_max)
            xy_d = torch.where(sel[:, None], xy_m, xy_d)
            within = torch.where(sel, within_m, within)
        u, v = _through_K(xy_d[:, 0], xy_d[:, 1], within, K[:, 0, 0], K[:, 0, 1], K[:, 0, 2], K[:, 1, 1],
                          K[:, 1, 2])
        return u, v, self.distorted[view]


class FrameLens(NamedTuple):
    """One view's lens, for projecting many points (voxel centres) into it."""

    distortion: Distortion
    """The view's distortion."""
    r_max: float
    """Undistorted normalised radius holding the view's image (:func:`~regnf.captures.distortion.check_invertible`)."""
    K: np.ndarray
    """(3, 3) float64 intrinsics that take distorted normalised coordinates to the pixels wanted."""

    def pixels(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel coordinates ``(u, v)`` of undistorted normalised ``(x, y)`` (any shape); -1 beyond :attr:`r_max`."""
        xy_d, within = distort_within(torch.stack([x, y], -1), self.distortion.model,
                                      self.distortion.coefficients(), self.r_max)
        K = [float(k) for k in self.K.ravel()]
        return _through_K(xy_d[..., 0], xy_d[..., 1], within, K[0], K[1], K[2], K[4], K[5])


def _through_K(xd: torch.Tensor, yd: torch.Tensor, within: torch.Tensor, fx: Any, skew: Any, cx: Any, fy: Any,
               cy: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """``K (x_d, y_d, 1)`` (skew included), and ``-1`` (outside every image) where not ``within``."""
    u = fx * xd + skew * yd + cx
    v = fy * yd + cy
    return torch.where(within, u, -1.0), torch.where(within, v, -1.0)
