"""The dense grid encoding: the per-level parallel path against the sequential one."""

from __future__ import annotations

import torch

from regnf.fields.dense_grid import DenseGridEncoding
from tests.core.helpers import torch_threads


def encoding() -> DenseGridEncoding:
    torch.manual_seed(0)
    return DenseGridEncoding(torch.tensor([2.0, 1.5, 1.0]), levels=4, finest_resolution=40, init_std=0.1)


def features_and_grads(enc: DenseGridEncoding, u: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    enc.zero_grad(set_to_none=True)
    y = enc(u)
    # A different weight per output column, so that a level's gradient landing on another
    # level's grid would show.
    (y * torch.arange(1, y.shape[1] + 1, dtype=y.dtype)).sum().backward()
    return y.detach(), [g.grad.clone() for g in enc.grids]


def test_parallel_levels_match_the_sequential_path_bit_for_bit() -> None:
    enc = encoding()
    u = torch.rand(5000, 3, generator=torch.Generator().manual_seed(1)) * 2.2 - 1.1  # some outside
    with torch_threads(1):  # one thread: the sequential path
        y1, g1 = features_and_grads(enc, u)
    with torch_threads(2):  # two threads: one level per thread
        y2, g2 = features_and_grads(enc, u)
    assert torch.equal(y1, y2)
    assert all(torch.equal(a, b) for a, b in zip(g1, g2))
    # And against the definition: each level is torch's grid_sample of that grid.
    g = u.view(1, 1, 1, -1, 3)
    ref = torch.nn.functional.grid_sample(enc.grids[2], g, padding_mode="border", align_corners=True)
    assert torch.equal(y2[:, 8:12], ref.view(4, -1).t().detach())


def test_positions_needing_a_gradient_get_it_on_either_thread_count() -> None:
    enc = encoding()
    u0 = torch.rand(300, 3, generator=torch.Generator().manual_seed(2)) * 1.6 - 0.8
    out = []
    for n in (1, 2):
        with torch_threads(n):
            u = u0.clone().requires_grad_(True)
            (gu,) = torch.autograd.grad(enc(u).sum(), u)
            out.append(gu)
    assert torch.equal(out[0], out[1])
    # Finite differences of the encoding along x agree with the autograd gradient, but where
    # the step crosses a cell face (trilinear features have a kink there: a few % of points).
    h = 1e-3
    e = torch.tensor([h, 0.0, 0.0])
    with torch.no_grad():
        fd = (enc(u0 + e).sum(dim=1) - enc(u0 - e).sum(dim=1)) / (2 * h)
    close = (out[1][:, 0] - fd).abs() <= 1e-2 * (1.0 + fd.abs())
    assert float(close.float().mean()) > 0.8


def _child_pool(queue) -> None:  # runs in a forked child
    from regnf.fields import dense_grid

    queue.put((len(dense_grid._POOLS), list(dense_grid._pool(2).map(abs, [-1, -2]))))


def test_a_forked_child_gets_pools_of_its_own() -> None:
    # The parent's pool has run work (its threads exist); a forked child inherits the pool
    # object but not its threads, and work sent to it would never run. (The child does no
    # torch work: torch's own OpenMP pool is not fork-safe, which is why our process pools
    # spawn.)
    import multiprocessing

    from regnf.fields import dense_grid

    assert list(dense_grid._pool(2).map(abs, [-3])) == [3]
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child_pool, args=(queue,))
    child.start()
    child.join(timeout=30)
    alive = child.is_alive()
    if alive:
        child.kill()
    assert not alive, "the child hung on the parent's thread pool"
    assert queue.get(timeout=5) == (0, [1, 2])
