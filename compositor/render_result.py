"""The image structure both renderers return."""

from __future__ import annotations

from typing import NamedTuple

import torch


class Render(NamedTuple):
    """One rendered view (tensors on the field's device).

    Depth is the z-depth along the optical axis in METRES (the field's world), 0 where
    the pixel hit nothing; ``mask`` tells hits from background. Normals are unit vectors in
    the WORLD frame (the field's ``to_world`` rotation applied), 0 on the background.
    """

    rgb: torch.Tensor
    """(h, w, 3) float in [0, 1]; the configured background where nothing was hit."""
    depth: torch.Tensor
    """(h, w) float: metres along the optical axis; 0 on the background."""
    normals: torch.Tensor
    """(h, w, 3) float: unit outward normals, world frame; 0 on the background."""
    instance_id: torch.Tensor
    """(h, w) int64: 0 the scene, i >= 1 a placed instance, -1 the background."""
    mask: torch.Tensor
    """(h, w) bool: the pixel shows a surface."""
    evals_per_pixel: torch.Tensor
    """(h, w) int64: field (SDF) evaluations spent on the pixel, composite costs included."""
    lookups_per_pixel: torch.Tensor
    """(h, w) int64: coarse distance-grid look-ups (empty-space skipping); 0 if unused."""
