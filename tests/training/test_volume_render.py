"""NeuS volume rendering: opacity from the SDF, and the optional training loss."""

from __future__ import annotations

import dataclasses

import torch

from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig
from regnf.training.training import RGBDTrainConfig, train_rgbd
from regnf.training.volume_render import render_rays_neus

from .test_training import TINY, capture  # noqa: F401  (capture is a fixture)


def test_opacity_is_one_through_the_init_sphere_and_zero_beside_it() -> None:
    torch.manual_seed(0)
    field = NeuralSDF(NeuralSDFConfig(levels=2, finest_resolution=16, base_resolution=8))
    # Rays along +x: through the centre (hits the radius-0.5 init sphere), and 0.95 off axis.
    origins = torch.tensor([[-1.0, 0.0, 0.0], [-1.0, 0.95, 0.0], [-1.0, 0.0, 0.95]])
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3).contiguous()
    near, far = torch.zeros(3), torch.full((3,), 1.0)
    rgb, opacity = render_rays_neus(field, origins, dirs, near, far, 256, inv_s=200.0)
    assert rgb.shape == (3, 3) and bool(((rgb >= 0) & (rgb <= 1)).all())
    assert opacity[0] > 0.95
    assert opacity[1] < 0.05 and opacity[2] < 0.05


def test_training_with_the_volume_colour_loss_lowers_it(capture) -> None:  # noqa: F811
    base = RGBDTrainConfig(steps=60, batch_surface=256, batch_free=128, batch_empty=128,
                           batch_eikonal=128, architecture=TINY, w_volume_color=1.0,
                           volume_rays=64, volume_samples=16)
    _, log = train_rgbd(capture, base, progress=False)
    first, last = log.losses[0]["volume_color"], log.losses[-1]["volume_color"]
    assert torch.isfinite(torch.tensor([first, last])).all()
    assert last < first
    _, off = train_rgbd(capture, dataclasses.replace(base, w_volume_color=0.0, steps=2), progress=False)
    assert off.losses[-1]["volume_color"] == 0.0
