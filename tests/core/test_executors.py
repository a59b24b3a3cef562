"""The executors: every task's outcome comes back, errors per task, threads pinned."""

from __future__ import annotations

from pathlib import Path

import pytest

from regnf.core.executors import ExecutorConfig, local_pool, run_tasks


def square_or_fail(x: int) -> tuple[int, int]:
    """x squared and the worker's torch thread count; raises for negative x."""
    import torch

    if x < 0:
        raise ValueError(f"negative input {x}")
    return x * x, torch.get_num_threads()


def test_local_pool_returns_every_outcome_and_the_errors() -> None:
    tasks = [3, -1, 4, -5, 0]
    outcomes = list(run_tasks(square_or_fail, tasks, ExecutorConfig(workers=2, threads_per_task=1)))
    assert sorted(o.index for o in outcomes) == list(range(len(tasks)))
    by_index = {o.index: o for o in outcomes}
    for i, x in enumerate(tasks):
        if x < 0:
            assert by_index[i].value is None
            assert by_index[i].error.startswith(f"ValueError: negative input {x}")
            assert "Traceback" in by_index[i].error
        else:
            assert by_index[i].error is None and by_index[i].value == (x * x, 1)


def test_threads_per_task_are_pinned() -> None:
    outcomes = list(run_tasks(square_or_fail, [2, 3], ExecutorConfig(workers=1, threads_per_task=2)))
    assert {o.value[1] for o in outcomes} == {2}


def test_tasks_run_in_a_given_pool_that_stays_open() -> None:
    # A caller's pool (started early) runs one batch of tasks after another, and is its to close.
    config = ExecutorConfig(workers=2, threads_per_task=1)
    with local_pool(2, 1) as pool:
        for batch in ([3, -1], [4, 5]):
            outcomes = {o.index: o for o in run_tasks(square_or_fail, batch, config, pool)}
            for i, x in enumerate(batch):
                assert outcomes[i].value == (None if x < 0 else (x * x, 1))
        assert pool.submit(abs, -2).result() == 2
    with pytest.raises(ValueError, match="ray"):
        list(run_tasks(square_or_fail, [1], ExecutorConfig(kind="ray"), pool))


def test_no_task_runs_nothing() -> None:
    assert list(run_tasks(square_or_fail, [], ExecutorConfig())) == []


@pytest.mark.parametrize("kwargs", [{"kind": "spark"}, {"workers": -1}, {"threads_per_task": 0},
                                    {"address": "auto"}])
def test_bad_settings_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        ExecutorConfig(**kwargs)


def test_a_pool_worker_ends_when_its_parent_is_killed(tmp_path: Path) -> None:
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "parent.py"
    script.write_text(
        "import os, sys, time\n"
        "from regnf.core.executors import local_pool\n"
        "if __name__ == '__main__':\n"
        "    with local_pool(1) as pool:\n"
        "        print(pool.submit(os.getpid).result(), flush=True)\n"
        "        pool.submit(time.sleep, 300)\n"
        "        time.sleep(300)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        worker = int(parent.stdout.readline())
        os.kill(parent.pid, signal.SIGKILL)  # the parent alone, as `kill -9 PID` does
        parent.wait(timeout=30)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.2)
        else:
            os.kill(worker, signal.SIGKILL)
            raise AssertionError("the worker outlived its parent by 20 s")
    finally:
        parent.kill()
