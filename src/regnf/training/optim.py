"""Optimiser and schedule shared by RGB-D training and mesh distillation."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tqdm import tqdm

from regnf.core.denormals import pool_denormals_flushed
from regnf.core.errors import RegnfError
from regnf.fields.neural_sdf import NeuralSDF


@dataclass
class OptimiserConfig:
    """The optimiser settings that RGB-D training and mesh distillation share (their configs derive from it)."""

    steps: int = 400
    """Optimisation steps."""
    lr_grid: float = 2e-2
    """Learning rate of the feature grids."""
    lr_mlp: float = 2e-3
    """Learning rate of the MLPs."""
    lr_final: float = 0.01
    """Learning rates at the last step, fraction of lr_grid and lr_mlp (docs/decisions/field-training.md)."""

    def __post_init__(self) -> None:
        name = type(self).__name__
        if isinstance(self.steps, bool) or int(self.steps) != self.steps or self.steps < 1:
            raise RegnfError(f"{name}.steps must be a whole number >= 1, got {self.steps}")
        for lr in ("lr_grid", "lr_mlp"):
            if not (math.isfinite(getattr(self, lr)) and getattr(self, lr) > 0):
                raise RegnfError(f"{name}.{lr} must be finite and > 0, got {getattr(self, lr)}")
        if not (math.isfinite(self.lr_final) and 0.0 <= self.lr_final <= 1.0):
            raise RegnfError(f"{name}.lr_final is a fraction of the learning rates, in [0, 1]; got {self.lr_final}")


def make_optimizer(
    field: NeuralSDF, lr_grid: float, lr_mlp: float, extra_groups: Sequence[dict] = (),
) -> torch.optim.AdamW:
    """AdamW with a larger learning rate for the feature grids than for the MLPs.

    Grid features are touched by few samples each step, so they need bigger steps than the
    MLP weights that every sample updates; neither decays. ``extra_groups``
    are further parameter groups trained alongside the field (the pose corrections of
    :mod:`regnf.training.pose_refinement`), each with its own ``lr``.
    """
    grid_params = list(field.encoding.parameters())
    grid_ids = {id(p) for p in grid_params}
    mlp_params = [p for p in field.parameters() if id(p) not in grid_ids]
    return torch.optim.AdamW(
        [
            {"params": grid_params, "lr": lr_grid, "weight_decay": 0.0},
            {"params": mlp_params, "lr": lr_mlp, "weight_decay": 0.0},
            *extra_groups,
        ],
        betas=(0.9, 0.99), eps=1e-15,
        # One fused kernel per step instead of a dozen passes over millions of grid
        # features (docs/decisions/implementation-speed.md).
        fused=True,
    )


def lr_factor(step: int, total: int, warmup: int = 50, final: float = 0.01) -> float:
    """Linear warm-up, then cosine decay from 1 to ``final`` at ``total`` steps."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * progress))


def finest_voxel(field: NeuralSDF) -> float:
    """Edge of a finest-level grid cell, in field units (the natural length scale of losses)."""
    extent = float((field.bounds[1] - field.bounds[0]).max())
    return extent / field.config.finest_resolution


LOG_EVERY = 50
"""Steps between two rows of a training log (the last step is always logged)."""


def optimise(
    field: NeuralSDF,
    config: OptimiserConfig,
    loss_at: Callable[[int], tuple[torch.Tensor, dict[str, torch.Tensor]]],
    desc: str = "train",
    progress: bool = True,
    postfix: dict[str, str] | None = None,
    extra_groups: Sequence[dict] = (),
) -> list[dict[str, float]]:
    """The training loop of RGB-D training and mesh distillation: AdamW (:func:`make_optimizer`)
    on the schedule :func:`lr_factor`, one step per call of ``loss_at``.

    Parameters
    ----------
    field : NeuralSDF
        Trained in place.
    config : OptimiserConfig
        Steps and learning rates.
    loss_at : callable
        ``loss_at(step) -> (loss, parts)``: the scalar loss of that step's batch and the named
        terms to log (scalar tensors).
    desc, progress : str, bool
        The progress bar's label, and whether it is shown.
    postfix : dict of str to str, optional
        Shown on the bar: label -> a logged term's name.
    extra_groups : sequence of dict
        Further parameter groups (:func:`make_optimizer`), on the same schedule.

    Returns
    -------
    list of dict
        Every :data:`LOG_EVERY` steps and at the last: ``step``, ``loss`` and the terms.
    """
    steps = config.steps
    opt = make_optimizer(field, config.lr_grid, config.lr_mlp, extra_groups)
    base_lrs = [g["lr"] for g in opt.param_groups]
    log: list[dict[str, float]] = []
    bar = tqdm(range(steps), desc=desc, disable=not progress, leave=False)
    # Denormals flushed on every torch thread: the softplus's backward and the kernels on torch's
    # second thread included, which the evaluations' own flushing does not reach (core.denormals).
    with pool_denormals_flushed():
        for step in bar:
            for g, lr in zip(opt.param_groups, base_lrs):
                g["lr"] = lr * lr_factor(step, steps, final=config.lr_final)
            loss, parts = loss_at(step)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if step % LOG_EVERY == 0 or step == steps - 1:
                entry = {"step": step, "loss": float(loss.detach()), **{k: float(v.detach()) for k, v in parts.items()}}
                log.append(entry)
                if postfix:
                    bar.set_postfix({label: f"{entry[key]:.3f}" for label, key in postfix.items()})
    return log
