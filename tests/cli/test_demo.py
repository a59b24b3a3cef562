"""The demo's step log: times each step and tells from the cache whether it made anything."""

from __future__ import annotations

from pathlib import Path

import pytest

from regnf.cli.demo import StepLog


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


def test_a_folder_without_the_demo_marker_is_never_taken_for_the_demos(tmp_path: Path) -> None:
    # Files that look like a demo's, with no marker saying the demo made them: refused, and with
    # --reuse still refused where the demo would write over them (nothing of them is removed).
    import dataclasses
    import json

    from regnf.cli.demo import DemoConfig, demo_folder

    out = tmp_path / "demo"
    (out / "stage").mkdir(parents=True)
    (out / "summary.json").write_text(json.dumps({"command": f"regnf demo --out {out}"}))
    with pytest.raises(ValueError, match=r"demo: is not empty and was not made by regnf demo"), \
            demo_folder(out, DemoConfig()):
        pass
    with pytest.raises(ValueError, match=r"demo/stage: exists and was not made by regnf demo"), \
            demo_folder(out, dataclasses.replace(DemoConfig(), reuse=True)):
        pass
    assert (out / "stage").is_dir() and (out / "summary.json").is_file()
