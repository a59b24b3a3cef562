"""The floater pool keeps matter where a view saw free space, and only that."""

from __future__ import annotations

import torch

from regnf.training.floater_pool import FloaterPool

BOUNDS = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
FLOATER_CENTER = torch.tensor([0.0, 0.2, 0.0])
FLOATER_RADIUS = 0.15


def sdf(x: torch.Tensor) -> torch.Tensor:
    """A wall filling x > 0.8 and a ball floating in front of it."""
    wall = 0.8 - x[:, 0]
    ball = (x - FLOATER_CENTER).norm(dim=-1) - FLOATER_RADIUS
    return torch.minimum(wall, ball)[:, None]


def seen_free(x: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
    """View 2 sees everything in front of the wall (x < 0.7) as free; views 0 and 1 see nothing
    (as if their depth stopped at the camera)."""
    return ((view == 2) & (x[:, 0] < 0.7)).float()


def mined(observed=None) -> FloaterPool:
    pool = FloaterPool(capacity=100_000, device=torch.device("cpu"))
    added = pool.mine(sdf, BOUNDS, 0.05, torch.zeros(3), seen_free, 3, observed)
    assert added == len(pool)
    return pool


def test_a_mining_pass_keeps_the_floater_and_not_the_wall() -> None:
    pool = mined()
    inside_ball = (pool.points - FLOATER_CENTER).norm(dim=-1) < FLOATER_RADIUS
    assert len(pool) > 50 and bool(inside_ball.all())
    # Every grid point inside the ball is found (the wall, negative but never seen free, is not).
    axes = [torch.arange(-1.0, 1.0, 0.05)] * 3
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    expected = int(((grid - FLOATER_CENTER).norm(dim=-1) < FLOATER_RADIUS).sum())
    assert len(pool) == expected
    assert bool((pool.views == 2).all())


def test_a_mining_pass_skips_what_no_view_observed() -> None:
    pool = mined(observed=lambda x: (x[:, 1] > 0.2).float())
    assert len(pool) > 0 and bool((pool.points[:, 1] > 0.2).all())
    assert len(pool) < len(mined()) * 0.75


def test_successive_offsets_find_other_points() -> None:
    pool = FloaterPool(capacity=100_000, device=torch.device("cpu"))
    pool.mine(sdf, BOUNDS, 0.05, torch.zeros(3), seen_free, 3)
    first = pool.points.clone()
    pool.mine(sdf, BOUNDS, 0.05, torch.full((3,), 0.025), seen_free, 3)
    second = pool.points[len(first):]
    assert len(second) > 0
    assert torch.cdist(second, first).min() > 0.02


def test_draw_moves_points_by_at_most_the_jitter_and_keeps_their_views() -> None:
    pool = FloaterPool(capacity=10, device=torch.device("cpu"))
    pool.add(torch.tensor([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]]), torch.tensor([3, 7]))
    gen = torch.Generator().manual_seed(0)
    x, v = pool.draw(400, 0.1, lambda n: torch.rand(n, generator=gen),
                     lambda high, n: torch.randint(high, (n,), generator=gen))
    near_first = x.norm(dim=-1) < 1.0
    assert bool((v[near_first] == 3).all()) and bool((v[~near_first] == 7).all())
    assert 0 < int(near_first.sum()) < 400
    origin = torch.where(near_first[:, None], torch.zeros(3), torch.full((3,), 5.0))
    assert float((x - origin).abs().max()) <= 0.1
    assert float((x - origin).abs().max()) > 0.05


def test_the_pool_keeps_the_newest_points_up_to_its_capacity() -> None:
    pool = FloaterPool(capacity=3, device=torch.device("cpu"))
    pool.add(torch.arange(6.0).view(2, 3), torch.tensor([0, 1]))
    pool.add(torch.arange(6.0, 12.0).view(2, 3), torch.tensor([2, 3]))
    assert len(pool) == 3 and pool.views.tolist() == [1, 2, 3]
    assert pool.points[0].tolist() == [3.0, 4.0, 5.0]
