"""Torch (and the OpenMP runtime it shares with Open3D) on one CPU thread, for repeatable results."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run the block on one CPU thread (the thread count is restored after).

    Torch's ``set_num_threads`` sets the OpenMP runtime that Open3D shares in this process, so
    this also makes Open3D's parallel RANSAC and ICP single-threaded.

    Why (measured):

    - Registration's refinement: with two threads the same inputs refined three times in one
      process ended at inlier fractions 0.8232, 0.8241 and 0.8241 (low-coverage ac-room, chair
      c, 150 steps); one thread gives the same bits every time, and it is not slower at these
      batch sizes (5.6 s against 5.7-6.4 s).
    - Open3D's RANSAC: with two threads its hypotheses depend on the scheduling. The chair c
      in the low-coverage atbl-room's wt box (mesh library) scored 0.2241 run alone and 0.2184
      in a pooled benchmark worker, and 0.2769 with one thread.
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)
