"""Floaters found in free space the training views saw, kept until training carves them.

Training's free-space terms draw their points along rays and uniformly in the bounds: a
floater a few centimetres across, in a room of tens of cubic metres, is hit a few times in a
whole schedule, and one Adam step a hit does not remove it while the surface terms keep
moving the hash-grid features it shares. :class:`FloaterPool` finds them and holds on to them:

- a mining pass evaluates the field on a jittered grid over the bounds (``spacing`` apart,
  only where the visibility grid says a view observed space) and keeps the points with a
  negative SDF that some training view sees in front of its surface: matter where a view
  looked through;
- each training step also hands in its uniform free-space points that are negative;
- each step draws points from the pool, jittered by up to half the spacing, and training's
  free-space term asks them to be positive wherever their witness view sees them as free.

A point enters the pool with the view that saw through it, so every constraint it brings is
one the depth images prove (the same test as training's free-space term); nothing is asked of
space no view saw.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

SeenFree = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``seen_free(x (n, 3), view (n,) long) -> (n,) float``: 1 where the view sees x as free."""

_EVAL_CHUNK = 1 << 18
"""Grid points evaluated at a time by a mining pass (bounded memory at any bounds)."""


class FloaterPool:
    """Points that were inside the field where a training view saw free space.

    Parameters
    ----------
    capacity : int
        Points kept; the oldest go first.
    device : torch.device
    """

    def __init__(self, capacity: int, device: torch.device) -> None:
        self.capacity = capacity
        self.points = torch.zeros(0, 3, device=device)
        self.views = torch.zeros(0, dtype=torch.long, device=device)

    def __len__(self) -> int:
        return self.points.shape[0]

    def add(self, points: torch.Tensor, views: torch.Tensor) -> None:
        """Keep ``points`` (n, 3), each seen free by training view ``views`` (n,) long."""
        self.points = torch.cat([self.points, points.detach()])[-self.capacity:]
        self.views = torch.cat([self.views, views])[-self.capacity:]

    @torch.no_grad()
    def mine(
        self,
        sdf: Callable[[torch.Tensor], torch.Tensor],
        bounds: torch.Tensor,
        spacing: float,
        offset: torch.Tensor,
        seen_free: SeenFree,
        view_count: int,
        observed: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> int:
        """One mining pass over a grid; returns the points added.

        Parameters
        ----------
        sdf : callable
            (n, 3) -> (n,) or (n, 1): the field being trained.
        bounds : (2, 3) float tensor
            The field's bounds.
        spacing : float
            Grid spacing, field units.
        offset : (3,) float tensor
            The grid's first point lies at ``bounds[0] + offset`` (draw it in [0, spacing) so
            that successive passes see different points).
        seen_free, view_count
            The training views' free-space test and their number.
        observed : callable, optional
            (n, 3) -> (n,) weight: grid points with weight 0 (no view saw them) are skipped
            before the field is evaluated.
        """
        start = bounds[0] + offset
        axes = [torch.arange(float(start[i]), float(bounds[1, i]), spacing, device=bounds.device)
                for i in range(3)]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        if observed is not None:
            grid = grid[observed(grid) > 0]
        inside = [chunk[sdf(chunk).reshape(-1) < 0] for chunk in grid.split(_EVAL_CHUNK)]
        candidates = torch.cat(inside) if inside else grid[:0]
        witness = torch.full((candidates.shape[0],), -1, dtype=torch.long, device=grid.device)
        for view in range(view_count):  # a few dozen views, each vectorised over the points
            free = seen_free(candidates, torch.full_like(witness, view)) > 0
            witness = torch.where((witness < 0) & free, torch.full_like(witness, view), witness)
        found = witness >= 0
        self.add(candidates[found], witness[found])
        return int(found.sum())

    def draw(self, n: int, jitter: float, rand: Callable[[int], torch.Tensor],
             randint: Callable[[int, int], torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(n, 3) points drawn with replacement, moved by up to ``jitter`` per axis, and (n,)
        their witness views. ``rand(k)`` and ``randint(high, k)`` are training's generators."""
        pick = randint(len(self), n)
        move = (rand(n * 3).view(n, 3) * 2.0 - 1.0) * jitter
        return self.points[pick] + move, self.views[pick]
