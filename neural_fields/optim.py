"""Optimiser and schedule shared by RGB-D training and mesh distillation."""

from __future__ import annotations

import math

import torch

from regnf.neural_fields.neural_sdf import NeuralSDF


def make_optimizer(
    field: NeuralSDF, lr_grid: float, lr_mlp: float, grid_decay: float = 0.0
) -> torch.optim.AdamW:
    """AdamW with a larger learning rate for the feature grids than for the MLPs.

    Grid features are touched by few samples each step, so they need bigger steps than the
    MLP weights that every sample updates. ``grid_decay`` (decoupled weight decay on the
    grids only) pulls features that no loss constrains back to zero, which removes the
    small floaters that fine-grid noise otherwise leaves in free space.
    """
    grid_params = list(field.encoding.parameters())
    grid_ids = {id(p) for p in grid_params}
    mlp_params = [p for p in field.parameters() if id(p) not in grid_ids]
    return torch.optim.AdamW(
        [
            {"params": grid_params, "lr": lr_grid, "weight_decay": grid_decay},
            {"params": mlp_params, "lr": lr_mlp, "weight_decay": 0.0},
        ],
        betas=(0.9, 0.99), eps=1e-15,
        # One fused kernel per step instead of a dozen passes over millions of grid
        # features: 9x faster on CPU (0.017 s vs 0.149 s for 11.7 M parameters).
        fused=True,
    )


def lr_factor(step: int, total: int, warmup: int = 50, final: float = 0.1) -> float:
    """Linear warm-up, then cosine decay from 1 to ``final`` at ``total`` steps."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * progress))


def finest_voxel(field: NeuralSDF) -> float:
    """Edge of a finest-level grid cell, in field units (the natural length scale of losses)."""
    extent = float((field.bounds[1] - field.bounds[0]).max())
    return extent / field.config.finest_resolution
