"""The training loop's schedule: warm-up, cosine decay, and where it ends."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from regnf.core.errors import RegnfError
from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig
from regnf.training import optim
from regnf.training.distill import DistillConfig
from regnf.training.training import RGBDTrainConfig

TINY = NeuralSDFConfig(levels=2, finest_resolution=8, base_resolution=4, hidden_dim=8, color_hidden_dim=8)


def test_the_schedule_warms_up_then_decays_to_its_final_fraction() -> None:
    assert optim.lr_factor(0, 100, warmup=10, final=0.01) == pytest.approx(0.1)
    assert optim.lr_factor(9, 100, warmup=10, final=0.01) == pytest.approx(1.0)
    assert optim.lr_factor(10, 100, warmup=10, final=0.01) == pytest.approx(1.0)
    # Half-way through the decay: the mean of the start and the end.
    assert optim.lr_factor(55, 100, warmup=10, final=0.01) == pytest.approx(0.505)
    assert optim.lr_factor(100, 100, warmup=10, final=0.01) == pytest.approx(0.01)


@pytest.mark.parametrize("final", [0.1, 0.01])
def test_optimise_ends_at_lr_final_of_each_rate(monkeypatch: pytest.MonkeyPatch, final: float) -> None:
    field = NeuralSDF(TINY)
    made: list[torch.optim.Optimizer] = []
    make = optim.make_optimizer
    monkeypatch.setattr(optim, "make_optimizer", lambda *a, **k: made.append(make(*a, **k)) or made[-1])

    def loss_at(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return field.sdf(torch.rand(16, 3)).square().mean(), {}

    steps, warmup = 60, 50
    config = optim.OptimiserConfig(steps=steps, lr_grid=0.02, lr_mlp=0.002, lr_final=final)
    optim.optimise(field, config, loss_at, progress=False)
    # The rate of the last step: cosine decay from 1 to ``final`` over steps - warmup.
    last = final + (1 - final) * 0.5 * (1 + math.cos(math.pi * (steps - 1 - warmup) / (steps - warmup)))
    grid, mlp = made[0].param_groups
    assert grid["lr"] == pytest.approx(0.02 * last) and mlp["lr"] == pytest.approx(0.002 * last)


@pytest.mark.parametrize(("setting", "value"), [("lr_final", -0.01), ("lr_final", 1.5), ("lr_final", math.nan),
                                                ("steps", 0), ("steps", 2.5), ("lr_grid", 0.0), ("lr_mlp", math.inf)])
def test_optimiser_settings_out_of_range_are_refused_by_the_config(setting: str, value: float) -> None:
    with pytest.raises(RegnfError, match=f"OptimiserConfig.{setting}"):
        optim.OptimiserConfig(**{setting: value})


def test_training_and_distillation_share_the_optimiser_settings() -> None:
    # One definition of each: the defaults are the shared config's, and both refuse alike.
    shared = {f.name for f in dataclasses.fields(optim.OptimiserConfig)}
    for config in (RGBDTrainConfig, DistillConfig):
        assert issubclass(config, optim.OptimiserConfig)
        assert {f.name: f.default for f in dataclasses.fields(config) if f.name in shared} == {
            f.name: f.default for f in dataclasses.fields(optim.OptimiserConfig)}
        with pytest.raises(RegnfError, match=f"{config.__name__}.steps"):
            config(steps=0)
