"""Which training frames a field is trained on: every frame, every N-th, or at most N evenly spaced.

A pure function of the capture's training frame indices, so that the same options select the
same frames on every run (the selection is part of a trained field's cache key where it is not
every training frame, :meth:`regnf.synthetic.cache.Cache.rgbd_field`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from regnf.core.errors import RegnfError


def evenly_spaced(count: int, limit: int) -> np.ndarray:
    """Positions ``0 .. count - 1`` thinned to at most ``limit``, evenly spaced, first and last kept.

    Parameters
    ----------
    count : int
        Number of items (>= 0).
    limit : int
        Most positions returned (>= 1).

    Returns
    -------
    (min(count, limit),) int64
        Increasing positions.
    """
    if count <= limit:
        return np.arange(count, dtype=np.int64)
    if limit == 1:
        return np.zeros(1, dtype=np.int64)
    # Distinct because the spacing (count - 1) / (limit - 1) is above 1.
    return np.round(np.linspace(0.0, count - 1, limit)).astype(np.int64)


def select_frames(train: Sequence[int], stride: int = 1, max_frames: int | None = None) -> list[int]:
    """The training frames kept: every ``stride``-th of ``train``, then at most ``max_frames`` of those.

    Parameters
    ----------
    train : sequence of int
        The capture's training frame indices (:meth:`regnf.captures.model.Capture.train_indices`).
    stride : int
        Keep ``train[0], train[stride], train[2 * stride], ...`` (``--stride``; >= 1).
    max_frames : int or None
        Then keep at most this many, evenly spaced (``--max-frames``; >= 1); None: no limit.

    Returns
    -------
    list of int
        Frame indices, in capture order; ``list(train)`` with the defaults.

    Raises
    ------
    ValueError
        ``stride`` or ``max_frames`` below 1 (the message names the option).
    """
    if stride < 1:
        raise RegnfError(f"--stride must be at least 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise RegnfError(f"--max-frames must be at least 1, got {max_frames}")
    kept = list(train)[::stride]
    if max_frames is not None:
        kept = [kept[i] for i in evenly_spaced(len(kept), max_frames)]
    return [int(i) for i in kept]
