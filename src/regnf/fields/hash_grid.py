"""Multi-resolution hash-grid encoding in plain torch (the alternative to dense grids).

Coarse levels that fit in the table are indexed densely (no collisions); finer levels hash
their integer corners. Kept for comparison and for very large scenes where dense grids
would not fit in memory; docs/encodings.md records its CPU throughput.
"""

from __future__ import annotations

import torch

from regnf.core.box_grid import grid_shape
from regnf.fields.dense_grid import initial_values, level_resolutions

_PRIMES = (1, 2654435761, 805459861)
_CORNERS = torch.tensor([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)])


class HashGridEncoding(torch.nn.Module):
    """Concatenated trilinear features from ``levels`` hashed grids.

    Parameters
    ----------
    extent : (3,) float
        Size of the box the grids cover (only the aspect ratio matters).
    levels, features, base_resolution, finest_resolution
        Grid pyramid; resolutions count cells along the longest axis.
    table_size_log2 : int
        Entries per level are at most ``2 ** table_size_log2``.
    """

    def __init__(
        self,
        extent: torch.Tensor,
        levels: int = 8,
        features: int = 2,
        base_resolution: int = 16,
        finest_resolution: int = 256,
        table_size_log2: int = 18,
        init_std: float = 1e-4,
    ) -> None:
        super().__init__()
        self.features = features
        self.table_size = 2**table_size_log2
        self.resolutions = level_resolutions(levels, base_resolution, finest_resolution)
        self.shapes = [grid_shape(r, extent) for r in self.resolutions]
        self.tables = torch.nn.ParameterList()
        for shape in self.shapes:
            n = (shape[0] + 1) * (shape[1] + 1) * (shape[2] + 1)
            self.tables.append(torch.nn.Parameter(initial_values((min(n, self.table_size), features), init_std)))
        self.register_buffer("corners", _CORNERS.clone(), persistent=False)

    @property
    def output_dim(self) -> int:
        return self.features * len(self.tables)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        """Features (n, levels * features) at ``u`` (n, 3) in [-1, 1]^3 (box coordinates)."""
        unit = ((u + 1.0) * 0.5).clamp(0.0, 1.0)
        corners = self.corners.to(u.device)
        out = []
        for shape, table in zip(self.shapes, self.tables):
            size = torch.tensor(shape, device=u.device, dtype=u.dtype)
            p = unit * size
            p0 = torch.minimum(p.floor(), size - 1).long()
            w = p - p0
            c = p0[:, None, :] + corners[None]  # (n, 8, 3) integer corners
            if table.shape[0] < self.table_size or (shape[0] + 1) * (shape[1] + 1) * (shape[2] + 1) <= self.table_size:
                idx = (c[..., 2] * (shape[1] + 1) + c[..., 1]) * (shape[0] + 1) + c[..., 0]
            else:
                idx = (c[..., 0] * _PRIMES[0]) ^ (c[..., 1] * _PRIMES[1]) ^ (c[..., 2] * _PRIMES[2])
                idx = idx % self.table_size
            weights = torch.where(corners[None].bool(), w[:, None, :], 1.0 - w[:, None, :]).prod(-1)
            out.append((table[idx] * weights[..., None]).sum(dim=1))
        return torch.cat(out, dim=-1)
