"""The training loop's schedule: warm-up, cosine decay, and where it ends."""

from __future__ import annotations

import math

import pytest
import torch

from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig
from regnf.training import optim

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
    optim.optimise(field, steps, loss_at, lr_grid=0.02, lr_mlp=0.002, lr_final=final, progress=False)
    # The rate of the last step: cosine decay from 1 to ``final`` over steps - warmup.
    last = final + (1 - final) * 0.5 * (1 + math.cos(math.pi * (steps - 1 - warmup) / (steps - warmup)))
    grid, mlp = made[0].param_groups
    assert grid["lr"] == pytest.approx(0.02 * last) and mlp["lr"] == pytest.approx(0.002 * last)



@pytest.mark.parametrize("final", [-0.01, 1.5, math.nan])
def test_a_final_fraction_outside_zero_to_one_is_refused_before_any_step(final: float) -> None:
    steps: list[int] = []

    def loss_at(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        steps.append(step)
        return torch.zeros((), requires_grad=True), {}

    with pytest.raises(ValueError, match="lr_final"):
        optim.optimise(NeuralSDF(TINY), 5, loss_at, lr_grid=0.02, lr_mlp=0.002, lr_final=final, progress=False)
    assert steps == []
