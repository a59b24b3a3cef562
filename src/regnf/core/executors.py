"""Run independent tasks in parallel: a local process pool, or a Ray cluster.

One entry point, :func:`run_tasks`, maps a module-level function over a list of task
arguments and yields each outcome as it completes. Both executors run every task in a fresh
worker process with the same pinned number of torch threads, so that a task computes the
same numbers wherever it runs (a float reduction split over a different number of threads
rounds differently). A task that raises does not stop the others: its outcome carries the
error and traceback instead of a value.

``local`` (the default) is a ``spawn`` process pool on this machine. ``ray`` submits the same
tasks to a Ray cluster (``pip install 'regnf[distributed]'``): the one at ``address``, one
already initialised in this process (a test starts its own), or else a local instance. Every
node must see the task's input and output paths at the same place (a shared file system)
and have this project installed.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

from regnf.core.errors import RegnfError

EXECUTORS = ("local", "ray")
"""The executors :func:`run_tasks` knows."""


@dataclass(frozen=True)
class ExecutorConfig:
    """Where and how wide tasks run."""

    kind: Literal["local", "ray"] = "local"
    """local: a process pool on this machine; ray: a Ray cluster (the `distributed` extra)."""
    workers: int = 0
    """Tasks at once (local: pool size; ray: CPUs of a local instance it starts); 0: CPU count / threads."""
    threads_per_task: int = 1
    """Torch threads per task, pinned so that results do not depend on where a task runs."""
    address: str | None = None
    """Ray cluster to join ('auto', 'ray://host:10001'); None: this process's Ray instance, or a new local one."""

    def __post_init__(self) -> None:
        if self.kind not in EXECUTORS:
            raise RegnfError(f"executor must be one of {EXECUTORS}, got {self.kind!r}")
        if self.workers < 0 or self.threads_per_task < 1:
            raise RegnfError(f"need workers >= 0 and threads_per_task >= 1, got {self.workers}, "
                             f"{self.threads_per_task}")
        if self.address is not None and self.kind != "ray":
            raise RegnfError("an address is for the ray executor only")

    @property
    def width(self) -> int:
        """Tasks run at once on this machine (local) or asked of a local Ray instance."""
        return self.workers or max(1, (os.cpu_count() or 1) // self.threads_per_task)


class TaskOutcome(NamedTuple):
    """What became of one task."""

    index: int
    """Position of the task in the list given to :func:`run_tasks`."""
    value: Any
    """The function's return value (None if it failed)."""
    error: str | None
    """``ExceptionType: message`` and the traceback, if the task raised (or its worker died)."""


def pin_threads(threads: int) -> None:
    """Pin this process's torch (and OpenMP / MKL) thread counts to ``threads``."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    import torch

    torch.set_num_threads(threads)


PARENT_POLL_S = 1.0
"""How often a pool worker checks that the process that started it is still there, seconds."""


def start_worker(threads: int, parent: int) -> None:
    """A pool worker's start: pin its threads, and end it when its parent (pid ``parent``) is gone.

    A run killed without its process group (``kill PID``, a job scheduler's SIGKILL) would
    otherwise leave its workers waiting for tasks that never come, holding their memory.
    """
    pin_threads(threads)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="regnf-parent-watch", daemon=True).start()


def call_pinned(fn: Callable[[Any], Any], threads: int, task: Any) -> tuple[Any, str | None]:
    """``fn(task)`` with pinned threads; an exception comes back as text (it may not pickle)."""
    pin_threads(threads)
    try:
        return fn(task), None
    except Exception as exc:  # noqa: BLE001 (recorded per task; the others go on)
        return None, f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"


def run_tasks(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    config: ExecutorConfig = ExecutorConfig(),
    pool: cf.ProcessPoolExecutor | None = None,
) -> Iterator[TaskOutcome]:
    """Run ``fn(task)`` for every task; yield outcomes in completion order.

    Parameters
    ----------
    fn : callable
        A module-level function (it is imported by name in the workers); its argument and
        return value must pickle.
    tasks : sequence
        One argument per task.
    config : ExecutorConfig
    pool : ProcessPoolExecutor, optional
        The local executor's pool (:func:`local_pool`, with ``config.threads_per_task``), kept
        open after, for a caller that started its workers early; None: a pool of these tasks'
        own. Not for the ray executor.

    Yields
    ------
    TaskOutcome
        One per task, as each finishes.
    """
    if pool is not None and config.kind != "local":
        raise RegnfError(f"a local pool was given to the {config.kind} executor")
    if not tasks:
        return
    if config.kind == "ray":
        yield from _run_ray(fn, tasks, config)
    elif pool is not None:
        yield from _run_in(pool, fn, tasks, config)
    else:
        with local_pool(min(config.width, len(tasks)), config.threads_per_task) as own:
            yield from _run_in(own, fn, tasks, config)


@contextlib.contextmanager
def local_pool(workers: int, threads_per_task: int = 1) -> Iterator[cf.ProcessPoolExecutor]:
    """A ``spawn`` process pool of ``workers`` processes with pinned torch threads, for callers
    that submit tasks as earlier ones finish (submit :func:`call_pinned`). Its workers are
    shut down when the block ends; on an exception, tasks not yet started are cancelled."""
    # spawn, not fork: a forked child inherits the parent's torch thread pools and locks.
    ctx = multiprocessing.get_context("spawn")
    pool = cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=start_worker,
                                  initargs=(threads_per_task, os.getpid()))
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _run_in(pool: cf.ProcessPoolExecutor, fn: Callable[[Any], Any], tasks: Sequence[Any],
            config: ExecutorConfig) -> Iterator[TaskOutcome]:
    futures = {pool.submit(call_pinned, fn, config.threads_per_task, t): i for i, t in enumerate(tasks)}
    try:
        for fut in cf.as_completed(futures):
            i = futures[fut]
            try:
                value, error = fut.result()
            except Exception as exc:  # noqa: BLE001 (the worker died: killed, out of memory)
                value, error = None, f"{type(exc).__name__}: {exc}"
            yield TaskOutcome(i, value, error)
    except BaseException:
        # Interrupted (Ctrl-C, a consumer that stopped early): do not start the rest.
        for fut in futures:
            fut.cancel()
        raise


def _run_ray(fn: Callable[[Any], Any], tasks: Sequence[Any], config: ExecutorConfig) -> Iterator[TaskOutcome]:
    try:
        import ray
    except ImportError as exc:
        raise ImportError("the ray executor needs Ray: pip install 'regnf[distributed]' (ray>=2.9)") from exc
    started = False
    if config.address is not None:
        if ray.is_initialized():
            ray.shutdown()
        ray.init(address=config.address, log_to_driver=False)
        started = True
    elif not ray.is_initialized():
        ray.init(num_cpus=config.width * config.threads_per_task, include_dashboard=False, log_to_driver=False)
        started = True
    try:
        remote = ray.remote(num_cpus=config.threads_per_task, max_retries=0)(call_pinned)
        refs = {remote.remote(fn, config.threads_per_task, t): i for i, t in enumerate(tasks)}
        try:
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    try:
                        value, error = ray.get(ref)
                    except Exception as exc:  # noqa: BLE001 (the worker died or the task was cancelled)
                        value, error = None, f"{type(exc).__name__}: {exc}"
                    yield TaskOutcome(refs[ref], value, error)
        except BaseException:
            for ref in refs:
                ray.cancel(ref, force=True)
            raise
    finally:
        if started:
            ray.shutdown()
