"""The one image structure every renderer returns.

The field renderers (:func:`regnf.render.sphere_render.render`,
:func:`regnf.render.volume_renderer.render_volume`) fill every entry; the mesh rasteriser
that makes the synthetic captures and the benchmarks' references
(:class:`regnf.synthetic.render.RGBDRenderer`) has no normals and no evaluation counts, and
leaves those entries None.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class Render(NamedTuple):
    """One rendered view (tensors on the renderer's device: a field's, or the CPU).

    Depth is the z-depth along the optical axis in METRES (the world of the field or mesh), 0
    where the pixel hit nothing; ``mask`` tells hits from background. Normals are unit vectors
    in the WORLD frame (a field's ``to_world`` rotation applied), 0 on the background.
    """

    rgb: torch.Tensor
    """(h, w, 3) float in [0, 1]; the configured background where nothing was hit."""
    depth: torch.Tensor
    """(h, w) float: metres along the optical axis; 0 on the background."""
    normals: torch.Tensor | None
    """(h, w, 3) float: unit outward normals, world frame; 0 on the background. None from the
    rasteriser."""
    instance_id: torch.Tensor
    """(h, w) int64: -1 the background. Field renderers: 0 the scene, i >= 1 a placed instance.
    The rasteriser: the id each mesh was given, -1 for unlabelled geometry too."""
    mask: torch.Tensor
    """(h, w) bool: the pixel shows a surface."""
    evals_per_pixel: torch.Tensor | None
    """(h, w) int64: field (SDF) evaluations spent on the pixel, composite costs included. None
    from the rasteriser."""
    lookups_per_pixel: torch.Tensor | None
    """(h, w) int64: coarse distance-grid look-ups (empty-space skipping); 0 if unused. None
    from the rasteriser."""
