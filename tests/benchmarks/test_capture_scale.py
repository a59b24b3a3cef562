"""``regnf bench capture-scale``: each run measured in a process of its own, refusals and deaths
reported instead of raised, and its checks before any work."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from regnf.benchmarks.capture_scale import fitting_stride, measure, run_child
from regnf.cli.app import main
from regnf.observations.sample_memory import training_bytes
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails

W, H = 48, 36


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str]:
    """Sample building on 3 and 6 frames of 48 x 36 and 2 training steps on all 6."""
    root = tmp_path_factory.mktemp("scale")
    out, md = root / "scale.json", root / "scale.md"
    rc = main(["bench", "capture-scale", "--frames", "3", "6", "--width", str(W), "--height", str(H),
               "--train-frames", "6", "--steps", "2", "--json", str(out), "--markdown", str(md),
               "--cache-dir", str(root / "cache")])
    assert rc == 0
    return json.loads(out.read_text()), md.read_text()


def test_every_run_reports_its_own_time_and_peak_memory(tiny_run) -> None:
    result, table = tiny_run
    cap = result["capture"]
    assert (cap["room"], cap["frames"], cap["width"], cap["height"]) == ("ac-room", 6, W, H)
    assert 0 < result["memory_available_gib"] <= result["memory_total_gib"]
    rows = result["rows"]
    assert [(r["stage"], r["frames"], r["status"]) for r in rows] == [
        ("build_samples", 3, "ok"), ("build_samples", 6, "ok"), ("train", 6, "ok")]
    for r in rows:
        assert r["pixels"] == r["frames"] * W * H and r["seconds"] > 0 and r["pixel_stride"] == 1
        assert 0 < r["start_rss_gib"] <= r["peak_rss_gib"] < r["memory_limit_gib"] and r["estimated_gib"] > 0
    assert rows[2]["estimated_gib"] == pytest.approx(training_bytes(6, H, W, 1) / 2**30)
    # Inside a room every pixel sees a wall, a floor or an object: one sample per pixel.
    assert [r["samples"] for r in rows[:2]] == [3 * W * H, 6 * W * H]
    assert rows[2]["steps"] == 2
    assert "| build_samples | 6 | 1 | 0.0 | ok |" in table and "| train | 6 | 1 | 0.0 | ok |" in table


def test_a_refused_or_dying_run_is_reported_not_raised(tiny_run, tmp_path: Path) -> None:
    result, _ = tiny_run
    capture = tmp_path / "capture"
    shutil.copytree(result["capture"]["folder"], capture)
    depth = capture / "000004_depth.npy"  # the fifth frame's depth, as meta_data.json names it
    depth.unlink()
    row = measure(capture, "build_samples", 6)
    assert row["status"] == "refused" and "suggested_stride" not in row  # not the memory check's refusal
    assert row["message"].endswith(f"frames[4].sensor_depth_path: file {depth} not found")
    # A child whose address space cannot even hold torch dies; its row says so.
    dead = run_child(capture, "build_samples", 6, memory_limit_gib=0.05)
    assert dead["status"] == "failed" and dead["exit_status"] != 0 and dead["memory_limit_gib"] == 0.05


def test_the_suggested_stride_is_the_smallest_the_memory_check_accepts() -> None:
    needs = [training_bytes(600, 480, 640, s) for s in (1, 2, 3, 4)]
    assert needs[0] > needs[1] > needs[2] > needs[3]
    assert fitting_stride(600, 480, 640, needs[0]) == 1
    assert fitting_stride(600, 480, 640, needs[2]) == 3 and fitting_stride(600, 480, 640, needs[2] - 1) == 4
    assert fitting_stride(600, 480, 640, 0) is None


def test_training_beyond_the_memory_check_is_refused_with_the_stride_that_fits(tiny_run, monkeypatch) -> None:
    result, _ = tiny_run
    free = training_bytes(6, H, W, 2)  # enough at stride 2, not at 1
    monkeypatch.setattr("regnf.core.preflight.available_memory_bytes", lambda: free)
    row = measure(Path(result["capture"]["folder"]), "train", 6, steps=1)
    assert row["status"] == "refused" and row["suggested_stride"] == 2 and "steps" not in row
    assert f"training 6 frames of {W}x{H} at pixel stride 1 needs about" in row["message"]


@pytest.mark.parametrize("args, problem", [
    (["--frames", "0", "10"], "--frames 0 10: every count must be at least 1"),
    (["--width", "4"], "--width/--height 4 x 480: each side must be at least 8 pixels"),
    (["--frames", "--train-frames", "0"], "nothing to measure"),
    (["--memory-limit-gib", "-1"], "must not be negative"),
    (["--pixel-stride", "0"], "--pixel-stride 0: must be at least 1"),
])
def test_a_plan_that_measures_nothing_is_refused_before_any_capture(tmp_path: Path, capsys, args, problem) -> None:
    before = snapshot(tmp_path)
    assert_fails(capsys, ["bench", "capture-scale", *args, "--json", str(tmp_path / "s.json"),
                          "--cache-dir", str(tmp_path / "cache")], problem)
    assert changes(before, snapshot(tmp_path)) == []
