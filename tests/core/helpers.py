"""Helpers shared by tests of threads: torch's thread count, a context held on another thread."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator

import torch


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with torch on ``n`` CPU threads; the caller's count comes back after."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def held_on_another_thread(enter: Callable[[], contextlib.AbstractContextManager[object]]) -> Iterator[None]:
    """Run the block while another thread is inside the context ``enter()`` (a lock, a limit);
    that thread leaves it after the block."""
    entered, release = threading.Event(), threading.Event()

    def hold() -> None:
        with enter():
            entered.set()
            release.wait(10)

    other = threading.Thread(target=hold)
    other.start()
    try:
        assert entered.wait(10)
        yield
    finally:
        release.set()
        other.join()
