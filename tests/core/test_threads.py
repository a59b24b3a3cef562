"""Calls side by side on threads that each run torch on one CPU thread."""

from __future__ import annotations

import multiprocessing
import threading

import pytest
import torch

from regnf.core.threads import map_one_thread_each, one_thread
from tests.core.helpers import held_on_another_thread


def test_results_come_in_item_order_and_every_call_runs_on_one_thread() -> None:
    seen: list[int] = []

    def fn(x: int) -> tuple[int, int]:
        return x * x, torch.get_num_threads()

    before = torch.get_num_threads()
    out = map_one_thread_each(fn, list(range(7)), workers=2, on_done=lambda: seen.append(1))
    assert [r for r, _ in out] == [x * x for x in range(7)]
    assert {n for _, n in out} == {1}
    assert len(seen) == 7
    assert torch.get_num_threads() == before


def test_calls_run_side_by_side() -> None:
    # Each call waits for the other at a barrier: run one after the other, the first would
    # time out waiting.
    barrier = threading.Barrier(2, timeout=30)

    def fn(x: int) -> int:
        barrier.wait()
        return x

    assert map_one_thread_each(fn, [1, 2], workers=2) == [1, 2]


def test_a_failed_call_raises_after_the_others_finish() -> None:
    finished: list[int] = []

    def fn(x: int) -> int:
        if x == 1:
            raise ValueError("item 1")
        finished.append(x)
        return x

    with pytest.raises(ValueError, match="item 1"):
        map_one_thread_each(fn, [0, 1, 2, 3], workers=2)
    assert sorted(finished) == [0, 2, 3]


def test_one_worker_maps_here_on_one_thread() -> None:
    main = threading.get_ident()
    out = map_one_thread_each(lambda x: (threading.get_ident(), torch.get_num_threads()), [0, 1], workers=1)
    assert out == [(main, 1), (main, 1)]


def test_a_map_inside_a_mapped_call_completes_on_that_thread() -> None:
    # Four outer calls keep both pool threads busy; their inner maps must not wait for them.
    def outer(x: int) -> tuple[list[int], set[int]]:
        me = threading.get_ident()
        inner = map_one_thread_each(lambda y: (10 * x + y, threading.get_ident()), [0, 1, 2], workers=2)
        return [v for v, _ in inner], {t for _, t in inner} - {me}

    out = map_one_thread_each(outer, [1, 2, 3, 4], workers=2)
    assert [v for v, _ in out] == [[10 * x + y for y in range(3)] for x in (1, 2, 3, 4)]
    assert all(not others for _, others in out)


def test_the_pool_threads_are_kept_between_maps() -> None:
    # Both calls wait for each other, so both of the pool's threads run one: its two threads.
    barrier = threading.Barrier(2, timeout=30)
    # (Thread objects, not idents: the system reuses a finished thread's ident.)
    first = set(map_one_thread_each(lambda _: (barrier.wait(), threading.current_thread())[1], [0, 1], workers=2))
    again = set(map_one_thread_each(lambda _: threading.current_thread(), range(8), workers=2))
    assert len(first) == 2 and again <= first and threading.current_thread() not in first


def _map_in_child(queue: multiprocessing.Queue) -> None:
    queue.put(map_one_thread_each(lambda x: x + 1, [1, 2, 3], workers=2))


def test_a_forked_child_maps_on_its_own_threads() -> None:
    # The parent's pool with both its threads started (each call waits for the other), which
    # a forked child has as objects but not as threads.
    barrier = threading.Barrier(2, timeout=30)
    map_one_thread_each(lambda x: barrier.wait(), [0, 1], workers=2)
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_map_in_child, args=(queue,))
    child.start()
    child.join(timeout=30)
    if child.exitcode is None:
        child.kill()
    assert child.exitcode == 0, "the child hung or failed"
    assert queue.get(timeout=5) == [2, 3, 4]


def test_same_bits_as_one_thread() -> None:
    # Reductions split over threads sum in another order; each call on one thread does not.
    g = torch.Generator().manual_seed(0)
    xs = [torch.randn(300_000, generator=g) for _ in range(4)]
    with one_thread():
        ref = [x.sum() for x in xs]
    assert all(torch.equal(a, b) for a, b in zip(map_one_thread_each(torch.sum, xs, workers=2), ref))


def test_the_callers_grad_mode_carries_over() -> None:
    # Torch's grad mode is per thread: a call made under the caller's no_grad must not build
    # graphs on its worker thread (nor lose them under enable_grad).
    x = torch.ones(3, requires_grad=True)
    with torch.no_grad():
        off = map_one_thread_each(lambda _: (x * 2).requires_grad, [0, 1], workers=2)
    on = map_one_thread_each(lambda _: (x * 2).requires_grad, [0, 1], workers=2)
    assert off == [False, False] and on == [True, True]


def test_open3d_runs_on_one_thread_in_the_block_and_gets_its_limit_back() -> None:
    # Open3D's RANSAC draws from one random generator on as many TBB threads as it may use:
    # its hypotheses depend on the scheduling unless the block limits it to one.
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    with one_thread():
        assert o3d.utility.get_max_threads() == 1
        with one_thread():
            assert o3d.utility.get_max_threads() == 1
        assert o3d.utility.get_max_threads() == 1  # the inner block leaves the outer's limit
    assert o3d.utility.get_max_threads() == before


def test_open3d_stays_on_one_thread_while_a_block_on_another_thread_runs() -> None:
    # The limit is the process's: a block that leaves on one thread must not lift it under a
    # block still running on another.
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    with held_on_another_thread(one_thread):
        with one_thread():
            pass
        assert o3d.utility.get_max_threads() == 1
    assert o3d.utility.get_max_threads() == before
