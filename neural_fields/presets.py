"""Training presets: the settings a library object and a room field are trained with.

They are measured defaults (docs/benchmarks.md): a library object trains in under 2 minutes
on 2 CPU cores, a room in about 5.
"""

from __future__ import annotations

from regnf.neural_fields.distill import DistillConfig
from regnf.neural_fields.neural_sdf import NeuralSDFConfig
from regnf.neural_fields.training import RGBDTrainConfig


def object_rgbd_preset(device: str = "cpu", seed: int = 0) -> RGBDTrainConfig:
    """A library object captured alone: 6-level dense grid up to 128 cells, 1000 steps."""
    return RGBDTrainConfig(steps=1000, device=device, seed=seed, architecture=NeuralSDFConfig())


def object_mesh_preset(device: str = "cpu", seed: int = 0) -> DistillConfig:
    """A library object distilled from its mesh: same architecture, 400 steps."""
    return DistillConfig(device=device, seed=seed, architecture=NeuralSDFConfig())


def scene_rgbd_preset(device: str = "cpu", seed: int = 0) -> RGBDTrainConfig:
    """A room seen from inside: 7 levels up to 256 cells, inside-out init, 1500 steps, the
    occluding-edge loss at weight 1 (``RGBDTrainConfig.w_edge``: measured there)."""
    return RGBDTrainConfig(
        steps=1500,
        device=device,
        seed=seed,
        w_edge=1.0,
        architecture=NeuralSDFConfig(
            levels=7, finest_resolution=256, inside_out=True, init_radius=0.9
        ),
    )
