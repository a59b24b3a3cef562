"""The demo's step log: times each step and tells from the cache whether it made anything."""

from __future__ import annotations

from pathlib import Path

import pytest

from regnf.demo import StepLog


def test_a_step_that_adds_to_the_cache_is_not_cached(tmp_path: Path) -> None:
    log = StepLog(tmp_path)
    (tmp_path / "fields").mkdir()
    with log.step("train", cacheable=True):
        (tmp_path / "fields" / "room.safetensors").write_bytes(b"x")
    with log.step("train again", cacheable=True):
        pass
    with log.step("render"):
        pass
    assert [s["cached"] for s in log.steps] == [False, True, False]
    assert all(s["seconds"] >= 0 for s in log.steps)


def test_a_failing_step_is_not_logged(tmp_path: Path) -> None:
    log = StepLog(tmp_path)
    with pytest.raises(RuntimeError), log.step("register"):
        raise RuntimeError("no registration was accepted")
    assert log.steps == []
