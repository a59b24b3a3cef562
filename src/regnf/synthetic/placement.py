"""Random non-overlapping placement of footprints in a rectangle.

Each footprint is bounded by a circle about its object's origin (the circumscribed circle of
its canonical xy footprint), which stays valid under any yaw; keeping circles apart by ``gap``
therefore keeps the true footprints apart by at least ``gap`` too.
"""

from __future__ import annotations

import numpy as np

from regnf.core.errors import RegnfError


def place_circles(
    radii: np.ndarray,
    half_extent: tuple[float, float],
    gap: float,
    margin: float,
    rng: np.random.Generator,
    max_tries: int = 4000,
    max_restarts: int = 100,
    context: str = "placement",
) -> np.ndarray:
    """Sample centres of non-overlapping circles inside a centred rectangle.

    Parameters
    ----------
    radii : (n,) float
        Circle radii, placed in the given order.
    half_extent : (2,) float
        The rectangle is ``[-hx, hx] x [-hy, hy]``.
    gap : float
        Minimum distance between two circles' boundaries.
    margin : float
        Minimum distance between a circle and the rectangle's sides.
    rng : numpy Generator
        Source of randomness (deterministic for a seed).

    Returns
    -------
    (n, 2) float64
        Circle centres.
    """
    radii = np.asarray(radii, dtype=np.float64)
    hx, hy = half_extent
    lim = np.stack([hx - margin - radii, hy - margin - radii], axis=1)
    if np.any(lim < 0):
        raise RegnfError(f"{context}: an object does not fit in the {2 * hx} x {2 * hy} m area")
    for _ in range(max_restarts):
        centres: list[np.ndarray] = []
        for i, r in enumerate(radii):  # sequential: each circle depends on the previous ones
            # Draw a batch of candidates at once and keep the first that fits.
            cand = rng.uniform(-lim[i], lim[i], size=(max_tries, 2))
            ok = np.ones(max_tries, dtype=bool)
            for j, c in enumerate(centres):
                ok &= np.linalg.norm(cand - c, axis=1) >= r + radii[j] + gap
            hits = np.flatnonzero(ok)
            if hits.size == 0:
                break
            centres.append(cand[hits[0]])
        else:
            return np.array(centres, dtype=np.float64).reshape(len(radii), 2)
    raise RuntimeError(f"{context}: could not place {len(radii)} objects without overlap")
