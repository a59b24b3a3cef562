"""Training presets: the settings a library object and a room field are trained with.

The step counts are where the surface error has converged. The held-out PSNR is what a short
schedule gives up (the colour converges more slowly than the geometry); every preset therefore
feeds the grid features to the colour head as well
(:attr:`~regnf.fields.neural_sdf.NeuralSDFConfig.color_grid_features`). Every preset ends
its learning-rate schedule at a hundredth of its start (``lr_final``, the configs' default), so
that the last steps of a short schedule do not move whole surfaces. The measurements behind
each choice: docs/decisions/field-training.md.
"""

from __future__ import annotations

import copy
import dataclasses

from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.training.distill import DistillConfig
from regnf.training.training import RGBDTrainConfig

OBJECT_RGBD = RGBDTrainConfig(steps=200, architecture=NeuralSDFConfig(color_grid_features=True))
"""A library object captured alone: 6-level dense grid up to 128 cells, 200 steps, grid features
to the colour head."""

OBJECT_MESH = DistillConfig(steps=200, batch=3072, eikonal_uniform=False,
                            architecture=NeuralSDFConfig(finest_resolution=64, color_grid_features=True))
"""A library object distilled from its mesh: 200 steps, the finest grid at 64 cells, 3072
near-surface samples a step and the eikonal term at the surface samples only
(:attr:`DistillConfig.eikonal_uniform`; docs/decisions/field-training.md)."""

SCENE_RGBD = RGBDTrainConfig(
    steps=400,
    w_edge=1.0,
    w_outline=1.0,
    carve_every=50,
    architecture=NeuralSDFConfig(levels=7, finest_resolution=256, inside_out=True, init_radius=0.9,
                                 color_grid_features=True),
)
"""A room seen from inside: 7 levels up to 256 cells, inside-out init, 400 steps, the
occluding-edge loss (``w_edge``) and the outline loss (``w_outline``) at weight 1, and the floater
pool from the 200th step with a mining pass every 50 (``carve_every``; docs/decisions/room-training-losses.md)."""


def object_rgbd_preset(device: str = "cpu", seed: int = 0) -> RGBDTrainConfig:
    """:data:`OBJECT_RGBD` on ``device`` with ``seed``."""
    return copy.deepcopy(dataclasses.replace(OBJECT_RGBD, device=device, seed=seed))  # the preset stays as it is


def object_mesh_preset(device: str = "cpu", seed: int = 0) -> DistillConfig:
    """:data:`OBJECT_MESH` on ``device`` with ``seed``."""
    return copy.deepcopy(dataclasses.replace(OBJECT_MESH, device=device, seed=seed))  # the preset stays as it is


def scene_rgbd_preset(device: str = "cpu", seed: int = 0) -> RGBDTrainConfig:
    """:data:`SCENE_RGBD` on ``device`` with ``seed``."""
    return copy.deepcopy(dataclasses.replace(SCENE_RGBD, device=device, seed=seed))  # the preset stays as it is
