"""Multi-resolution dense feature grids, sampled with ``grid_sample``.

Dense grids sampled by torch's fused trilinear kernel are the default encoding: at the sizes we
train they evaluate faster than a pure-torch hash grid (docs/encodings.md).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import torch
import torch.nn.functional as F

from regnf.core.box_grid import grid_shape
from regnf.core.errors import RegnfError


def level_resolutions(levels: int, base: int, finest: int) -> list[int]:
    """Geometric progression of ``levels`` grid resolutions from ``base`` to ``finest``."""
    if levels < 1 or base < 2 or finest < base:
        raise RegnfError(f"bad grid levels: levels={levels}, base={base}, finest={finest}")
    if levels == 1:
        return [finest]
    growth = (finest / base) ** (1.0 / (levels - 1))
    return [round(base * growth**level) for level in range(levels)]


def initial_values(shape: tuple[int, ...], std: float) -> torch.Tensor:
    """Random normal values of ``std``, or, on the meta device (a skeleton whose values will be
    loaded, :func:`regnf.io.checkpoint.load_field`), an empty tensor: drawing there
    would import torch's compiler stack, a second per process, for values nobody reads."""
    if torch.empty(0).is_meta:
        return torch.empty(shape)
    return torch.randn(shape) * std

class DenseGridEncoding(torch.nn.Module):
    """Concatenated trilinear features from ``levels`` dense grids.

    Parameters
    ----------
    extent : (3,) float
        Size of the box the grids cover (only the aspect ratio matters).
    levels, features, base_resolution, finest_resolution
        Grid pyramid; resolutions count cells along the longest axis.
    """

    def __init__(
        self,
        extent: torch.Tensor,
        levels: int = 6,
        features: int = 4,
        base_resolution: int = 16,
        finest_resolution: int = 128,
        init_std: float = 1e-4,
    ) -> None:
        super().__init__()
        self.features = features
        self.resolutions = level_resolutions(levels, base_resolution, finest_resolution)
        self.grids = torch.nn.ParameterList()
        for res in self.resolutions:
            nx, ny, nz = grid_shape(res, extent)
            # grid_sample indexes a 5-D volume as (N, C, D, H, W) with coordinates (x, y, z)
            # mapping to (W, H, D): store z-major so that x runs along W.
            self.grids.append(torch.nn.Parameter(initial_values((1, features, nz, ny, nx), init_std)))

    @property
    def output_dim(self) -> int:
        return self.features * len(self.grids)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        """Features (n, levels * features) at ``u`` (n, 3) in [-1, 1]^3 (box coordinates)."""
        g = u.view(1, 1, 1, -1, 3).to(self.grids[0].dtype)
        threads = torch.get_num_threads()
        if g.device.type == "cpu" and threads > 1 and not g.requires_grad and len(self.grids) > 1:
            return _LevelsInParallel.apply(g, threads, *self.grids)
        feats = [
            F.grid_sample(grid, g, mode="bilinear", padding_mode="border", align_corners=True)
            .view(self.features, -1)
            .t()
            for grid in self.grids
        ]
        return torch.cat(feats, dim=-1)


_POOLS: dict[int, ThreadPoolExecutor] = {}
# A forked child inherits the pools but not their threads: it starts its own.
os.register_at_fork(after_in_child=_POOLS.clear)


def _pool(threads: int) -> ThreadPoolExecutor:
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="grid-level")
    return _POOLS[threads]


class _LevelsInParallel(torch.autograd.Function):
    """The levels' trilinear look-ups, and their gradients, one level per CPU thread.

    Torch's CPU kernels of the 3-D ``grid_sample`` and of its backward run on one thread
    whatever ``torch.get_num_threads()`` says (they split the work over the batch, and ours is
    one volume), and they were half of a training step. The levels are independent, so they
    run side by side on a pool of that many threads (the kernels release the GIL). The result
    is the same tensor as the sequential path's, bit for bit: each level is the same kernel on
    the same inputs. Only for sample positions that need no gradient (training's samples);
    the positions' gradient and the double backward stay on the sequential path.
    """

    @staticmethod
    def forward(ctx, g: torch.Tensor, threads: int, *grids: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        # g: (1, 1, 1, n, 3) sample positions; grids: (1, C, D, H, W) per level.
        def one(grid: torch.Tensor) -> torch.Tensor:
            out = F.grid_sample(grid, g, mode="bilinear", padding_mode="border", align_corners=True)
            return out.view(grid.shape[1], -1).t()

        feats = list(_pool(threads).map(one, grids))
        ctx.save_for_backward(g, *grids)
        ctx.threads = threads
        return torch.cat(feats, dim=-1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        # grad: (n, levels * C).
        g, *grids = ctx.saved_tensors
        parts = grad.split([grid.shape[1] for grid in grids], dim=-1)

        def one(i: int) -> torch.Tensor | None:
            if not ctx.needs_input_grad[2 + i]:
                return None
            go = parts[i].t().reshape(1, -1, 1, 1, g.shape[3])
            # interpolation 0 = bilinear, padding 1 = border, as in forward.
            grad_grid, _ = torch.ops.aten.grid_sampler_3d_backward(
                go, grids[i], g, 0, 1, True, [True, False]
            )
            return grad_grid

        # Finest (largest) levels first, so that the pool's threads finish together.
        order = sorted(range(len(grids)), key=lambda i: -grids[i].numel())
        done = dict(zip(order, _pool(ctx.threads).map(one, order)))
        return (None, None, *(done[i] for i in range(len(grids))))
