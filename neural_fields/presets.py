"""Training presets: the settings a library object and a room field are trained with.

They are measured defaults (docs/benchmarks.md, "Fields" and "Training steps against
accuracy"). The step counts are where the surface error has converged: a fifth of the steps an
earlier preset took for an RGB-D object (1000), half for a mesh (400), about a quarter for a
room (1500), at the same or a lower surface error. On 2 CPU cores an RGB-D object then trains
in 13-36 s, a mesh at 64 cells with 3072 samples a step in 5.5-8 s (the bar is 10) and a full-coverage room in 53-83 s,
depending on the hour (this machine's speed drifts). The held-out PSNR is what
a short schedule gives up (the colour converges more slowly than the geometry); every preset
therefore feeds the grid features to the colour head as well
(:attr:`~regnf.neural_fields.neural_sdf.NeuralSDFConfig.color_grid_features`, measured
2026-12-05 on 4 held-out views with the same steps and time: the full-coverage ac-room 23.3 ->
26.8 dB, the armchair ``fc`` from RGB-D 28.7 -> 30.0 dB). Every preset ends its learning-rate
schedule at a hundredth of its start (``lr_final``, the configs' default): with a tenth the
last steps of a short schedule still moved the rooms' surfaces by 1-2 mm.
"""

from __future__ import annotations

from regnf.neural_fields.distill import DistillConfig
from regnf.neural_fields.neural_sdf import NeuralSDFConfig
from regnf.neural_fields.training import RGBDTrainConfig


def object_rgbd_preset(device: str = "cpu", seed: int = 0) -> RGBDTrainConfig:
    """A library object captured alone: 6-level dense grid up to 128 cells, 200 steps, grid
    features to the colour head."""
    return RGBDTrainConfig(steps=200, device=device, seed=seed,
                           architecture=NeuralSDFConfig(color_grid_features=True))


def object_mesh_preset(device: str = "cpu", seed: int = 0) -> DistillConfig:
    """A library object distilled from its mesh: 200 steps (at 100 the demo's discovery left the
    mc chair unmatched), the finest grid at 64 cells, not 128, and 3072 near-surface samples a
    step, not 4096. Measured on 2 cores (docs/benchmarks.md, "Distilling at 64 cells"): 7-9 s a
    chair where 128 took 10-12 s, the same surface error (fc 0.020 / 0.021 %, mc 0.018 / 0.020 %
    mean), 0.5-1.2 dB less held-out PSNR, and the low-coverage registration benchmark with this
    library the same (10 of 11 accepted, 9 within the bars, with either grid). The smaller batch
    ("A smaller batch for the meshes"): fc 11.2 -> 8.7 s, mc 9.6 -> 7.9 s and t 8.3 -> 6.6 s in
    one slow hour, mean surface error 0.021 -> 0.023 %, 0.019 -> 0.022 % and 0.028 -> 0.031 %
    (the bar is 0.3 %); 160 steps instead saved as much and lost twice the accuracy. The
    eikonal term at the surface samples only (:attr:`DistillConfig.eikonal_uniform`)."""
    return DistillConfig(steps=200, batch=3072, eikonal_uniform=False, device=device, seed=seed,
                         architecture=NeuralSDFConfig(finest_resolution=64, color_grid_features=True))


def scene_rgbd_preset(device: str = "cpu", seed: int = 0) -> RGBDTrainConfig:
    """A room seen from inside: 7 levels up to 256 cells, inside-out init, 400 steps, the
    occluding-edge loss at weight 1 (``RGBDTrainConfig.w_edge``: measured there), the outline
    loss at weight 1 (``w_outline``: it brings the low-coverage registration back to 11 of 11)
    and the floater pool from the 200th step, a mining pass every 50 (``carve_every``: without
    it the outline loss leaves floaters in free space the views saw)."""
    return RGBDTrainConfig(
        steps=400,
        device=device,
        seed=seed,
        w_edge=1.0,
        w_outline=1.0,
        carve_every=50,
        architecture=NeuralSDFConfig(
            levels=7, finest_resolution=256, inside_out=True, init_radius=0.9, color_grid_features=True
        ),
    )
