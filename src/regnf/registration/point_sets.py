"""Small operations on point sets: nearest neighbours, one point per voxel, random unit
directions, a bounding radius."""

from __future__ import annotations

import torch


class NearestPoints:
    """Nearest-neighbour lookup into a fixed point set (KD-tree on CPU, brute force on GPU)."""

    CHUNK = 4096

    def __init__(self, points: torch.Tensor) -> None:
        # Double precision on both paths (the KD-tree's), whatever the points' dtype: the
        # queries come in float64 and the nearest point must not depend on the device.
        self.points = points.detach().double()
        self.tree = None
        if points.device.type == "cpu":
            from scipy.spatial import cKDTree

            self.tree = cKDTree(self.points.numpy())

    def query(self, x: torch.Tensor) -> torch.Tensor:
        """(n,) long index of the nearest point to each query (n, 3); no gradient."""
        x = x.detach()
        if self.tree is not None:
            _, idx = self.tree.query(x.double().numpy(), k=1)
            return torch.as_tensor(idx, dtype=torch.long)
        x = x.double()
        parts = [torch.cdist(x[i:i + self.CHUNK], self.points).argmin(dim=1)
                 for i in range(0, x.shape[0], self.CHUNK)]
        return torch.cat(parts)


def voxel_new(existing: torch.Tensor, candidates: torch.Tensor, voxel: float) -> torch.Tensor:
    """(m,) bool: candidates (m, 3) in voxels free of ``existing`` (n, 3), first one per voxel."""
    m = candidates.shape[0]
    if m == 0:
        return torch.zeros(0, dtype=torch.bool, device=candidates.device)
    keys = torch.floor(torch.cat([existing, candidates]) / voxel).long()
    _, inv = torch.unique(keys, dim=0, return_inverse=True)
    n_vox = int(inv.max()) + 1
    taken = torch.zeros(n_vox, dtype=torch.bool, device=keys.device)
    taken[inv[: existing.shape[0]]] = True
    cinv = inv[existing.shape[0]:]
    order = torch.arange(m, device=keys.device)
    first = torch.full((n_vox,), m, dtype=torch.long, device=keys.device)
    first.scatter_reduce_(0, cinv, order, reduce="amin")
    return (~taken[cinv]) & (first[cinv] == order)


def unit_directions(n: int, gen: torch.Generator, like: torch.Tensor) -> torch.Tensor:
    """(n, 3) uniformly random unit vectors (drawn on the CPU: reproducible on any device)."""
    u = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True).clamp(min=1e-12)
    return u.to(device=like.device, dtype=like.dtype)


def bounding_radius(x: torch.Tensor) -> float:
    """Radius of the bounding sphere about the AABB centre of points (n, 3)."""
    centre = 0.5 * (x.min(dim=0).values + x.max(dim=0).values)
    return float((x - centre).norm(dim=1).max())
