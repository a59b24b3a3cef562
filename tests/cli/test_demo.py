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


def test_a_demo_folder_of_an_earlier_version_is_adopted(tmp_path: Path) -> None:
    import json

    from regnf.cli.demo import DemoConfig, demo_folder

    out = tmp_path / "demo"
    (out / "stage").mkdir(parents=True)
    (out / "summary.json").write_text(json.dumps({"command": f"regnf demo --out {out}"}))
    (out / "ac-room.usdz").write_bytes(b"PK")
    with demo_folder(out, DemoConfig()) as folder:  # made by the demo before markers: its own
        assert {"stage", "summary.json", "ac-room.usdz"} <= folder.entries
        folder.remove("stage")
    assert not (out / "stage").exists()
    other = tmp_path / "other"
    other.mkdir()
    (other / "summary.json").write_text(json.dumps({"command": "my own tool"}))
    with pytest.raises(ValueError, match=r"other: is not empty and was not made by regnf demo"), \
            demo_folder(other, DemoConfig()):
        pass

