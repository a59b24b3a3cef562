"""Encoding benchmark: CPU throughput of dense grid_sample pyramids against a hash grid.

This is the measurement behind the default encoding (docs/encodings.md): points per second
through the encoding plus the SDF MLP, forward only and forward + backward (training).
"""

from __future__ import annotations

import time

import torch

from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig

CANDIDATES: dict[str, NeuralSDFConfig] = {
    "dense L6 F4 16-128": NeuralSDFConfig(encoding="dense", levels=6, features_per_level=4, finest_resolution=128),
    "dense L7 F4 16-256": NeuralSDFConfig(encoding="dense", levels=7, features_per_level=4, finest_resolution=256),
    "hash L8 F2 16-256 T2^18": NeuralSDFConfig(encoding="hash", levels=8, features_per_level=2,
                                              finest_resolution=256, hash_table_size_log2=18),
    "hash L16 F2 16-1024 T2^19": NeuralSDFConfig(encoding="hash", levels=16, features_per_level=2,
                                                finest_resolution=1024, hash_table_size_log2=19),
}


def time_config(config: NeuralSDFConfig, n: int = 32768, reps: int = 5, device: str = "cpu") -> dict:
    """Throughput (points / s) of one architecture: forward, and forward + backward."""
    torch.manual_seed(0)
    field = NeuralSDF(config).to(device)
    x = torch.rand(n, 3, device=device) * 2 - 1
    field.sdf(x).sum().backward()  # warm-up
    with torch.no_grad():
        t = time.perf_counter()
        for _ in range(reps):
            field.sdf(x)
        fwd = n * reps / (time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(reps):
        field.zero_grad(set_to_none=True)
        field.sdf(x).sum().backward()
    bwd = n * reps / (time.perf_counter() - t)
    params = sum(p.numel() for p in field.encoding.parameters())
    return {"forward_pts_per_s": round(fwd), "train_pts_per_s": round(bwd), "grid_parameters": params}


def run_encodings_benchmark(device: str = "cpu") -> list[dict]:
    """One row per candidate encoding."""
    return [{"encoding": name, **time_config(cfg, device=device)} for name, cfg in CANDIDATES.items()]


def markdown_table(rows: list[dict]) -> str:
    head = "| encoding | grid parameters | forward Mpts/s | forward+backward Mpts/s |\n|---|---|---|---|\n"
    return head + "".join(
        f"| {r['encoding']} | {r['grid_parameters'] / 1e6:.2f} M | {r['forward_pts_per_s'] / 1e6:.2f} | "
        f"{r['train_pts_per_s'] / 1e6:.2f} |\n"
        for r in rows
    )
