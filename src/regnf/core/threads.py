"""Torch and Open3D on one CPU thread, for repeatable results; independent calls side by side,
each on one thread (:func:`map_one_thread_each`)."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import TypeVar

import torch

T = TypeVar("T")
R = TypeVar("R")


_open3d_lock = threading.Lock()
_open3d_holders = 0  # blocks, on any thread, inside _open3d_one_thread
_open3d_before = 0  # Open3D's thread limit when the first of them entered


@contextlib.contextmanager
def _open3d_one_thread() -> Iterator[None]:
    """Open3D on one thread for the block, when this process has loaded it.

    Open3D (0.20) parallelises with oneTBB, whose thread limit is one for the whole process
    (``open3d.utility.set_max_threads``), not torch's OpenMP setting: the first block to enter,
    on any thread, sets it to one, and the last to leave sets it back. A module that calls
    Open3D imports it first, so a block entered before that import has no Open3D call to
    limit; checking ``sys.modules`` spares the half second of importing it in processes that
    never use it (the renderer's workers).
    """
    global _open3d_holders, _open3d_before
    o3d = sys.modules.get("open3d")
    if o3d is None:
        yield
        return
    with _open3d_lock:
        if _open3d_holders == 0:
            _open3d_before = o3d.utility.get_max_threads()
            o3d.utility.set_max_threads(1)
        _open3d_holders += 1
    try:
        yield
    finally:
        with _open3d_lock:
            _open3d_holders -= 1
            if _open3d_holders == 0:
                o3d.utility.set_max_threads(_open3d_before)


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Run the block on one CPU thread (torch's thread count on this thread, and Open3D's
    limit for the process while any such block runs; both restored after).

    Why: on more threads the refinement's sums and Open3D's RANSAC (whose threads draw from one
    random generator in the order they reach it) depend on the scheduling, and one thread gives
    the same bits every time at no cost in speed at registration's batch sizes
    (docs/decisions/registration-refinement.md, docs/decisions/registration-initialisation.md).
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with _open3d_one_thread():
            yield
    finally:
        torch.set_num_threads(n)


_pools: dict[int, ThreadPoolExecutor] = {}  # by thread count; kept for the process's life
_pools_lock = threading.Lock()
_worker = threading.local()  # .active on the pools' threads


def _forget_pools() -> None:
    # A forked child inherits the pools but not their threads (nor a consistent lock).
    global _pools_lock
    _pools.clear()
    _pools_lock = threading.Lock()


os.register_at_fork(after_in_child=_forget_pools)


def _mark_worker() -> None:
    _worker.active = True


def _pool(workers: int) -> ThreadPoolExecutor:
    """The process's pool of ``workers`` threads for :func:`map_one_thread_each`.

    Kept, not made per call: a thread's start waits for the interpreter lock, which the other
    side's Python holds for up to the switch interval (5 ms), and a registration maps many
    times (docs/decisions/implementation-speed.md).
    """
    with _pools_lock:
        pool = _pools.get(workers)
        if pool is None:
            pool = _pools[workers] = ThreadPoolExecutor(
                max_workers=workers, thread_name_prefix="one-thread-each", initializer=_mark_worker)
        return pool


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; the whole machine without one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def worker_count(workers: int | None = None) -> int:
    """``workers``, or by default one per usable core, at most ``torch.get_num_threads()``."""
    return workers if workers is not None else max(1, min(usable_cores(), torch.get_num_threads()))


def map_one_thread_each(fn: Callable[[T], R], items: Sequence[T], workers: int | None = None,
                        on_done: Callable[[], None] | None = None) -> list[R]:
    """``[fn(x) for x in items]``, the calls side by side on threads that each run on one CPU thread.

    Every call runs single-threaded, so a call of pure torch work on inputs no other call
    changes gives the bits of the sequential map on one thread, on any machine (tested for the
    renderer: ``tests/compositor/test_render_folder.py``). Torch's kernels release the
    interpreter lock, so two such calls overlap on two cores, where one call on two threads
    leaves a core idle much of the time: the 3-D ``grid_sample`` runs on one thread whatever the
    setting, and the small batches of a sphere tracer's last steps do not split. Open3D's
    ICP and features let go of the lock too and, limited to one thread by :func:`one_thread`,
    give the same bits side by side (:mod:`regnf.registration.initialisation`). Discovery
    examines its candidates side by side in worker processes instead
    (:mod:`regnf.registration.discovery_workers`).

    Each call runs in the caller's grad mode (torch keeps it per thread: a call made under
    ``torch.no_grad()`` builds no graph on its worker thread either).

    Parameters
    ----------
    fn : callable
        Called once per item.
    items : sequence
    workers : int, optional
        Threads (default: :func:`worker_count`; at most the number of items), of a pool the
        process keeps (:func:`_pool`); 1, or a call from one of the pool's threads, runs the
        map here, on one thread.
    on_done : callable, optional
        Called (on this thread) after each call finishes, for a progress bar.

    Returns
    -------
    list
        ``fn(item)`` in the order of ``items``. The first call that raised (in item order)
        raises here, once every call has finished.
    """
    workers = max(1, min(worker_count(workers), len(items)))
    with one_thread():  # new threads take this count when torch first runs on them
        # A call made on a pool thread runs its map here: the pool's threads waiting on work
        # queued behind them could otherwise all wait (the results are the same bits).
        if workers == 1 or getattr(_worker, "active", False):
            out = []
            for x in items:
                out.append(fn(x))
                if on_done is not None:
                    on_done()
            return out

        grad = torch.is_grad_enabled()  # thread-local in torch: the caller's no_grad carries over

        def call(x: T) -> R:
            torch.set_num_threads(1)  # this thread's OpenMP setting, in case it ran torch before
            with torch.set_grad_enabled(grad):
                return fn(x)

        futures = [_pool(workers).submit(call, x) for x in items]
        for _ in as_completed(futures):
            if on_done is not None:
                on_done()
        return [f.result() for f in futures]
