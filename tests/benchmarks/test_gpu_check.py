"""``regnf bench gpu-check``: the path ``make gpu-check`` takes on a GPU, run on ``--device`` at
the tiny size (the CPU in CI), and its checks before any work."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from regnf.benchmarks.registration import METHODS, QUICK_PAIRS
from regnf.benchmarks.render import QUICK_RENDERERS
from regnf.cli.app import main

# A pytest --junitxml report with one test of each outcome.
JUNIT = """<?xml version="1.0" encoding="utf-8"?>
<testsuites><testsuite name="pytest" errors="0" failures="1" skipped="1" tests="3">
<testcase classname="tests.a" name="test_ok" time="0.1"/>
<testcase classname="tests.a" name="test_bad" time="0.1"><failure message="x">boom</failure></testcase>
<testcase classname="tests.b" name="test_skip" time="0"><skipped message="s"/></testcase>
</testsuite></testsuites>
"""


@pytest.mark.cuda
def test_every_part_runs_on_the_device_at_the_tiny_size(tmp_path: Path, device: str) -> None:
    junit = tmp_path / "tests.xml"
    junit.write_text(JUNIT)
    out, md = tmp_path / "check.json", tmp_path / "check.md"
    rc = main(["bench", "gpu-check", "--device", device, "--size", "tiny", "--tests", str(junit),
               "--json", str(out), "--markdown", str(md), "--cache-dir", str(tmp_path / "cache")])
    assert rc == 0
    result = json.loads(out.read_text())
    meta = result["meta"]
    assert meta["device"] == device and meta["size"] == "tiny"
    assert meta["device_name"] == (torch.cuda.get_device_name(device) if device.startswith("cuda") else "cpu")
    assert result["tests"] == {"file": str(junit), "tests": 3, "passed": 1, "failed": 1, "errors": 0,
                               "skipped": 1, "failures": ["tests.a::test_bad"]}

    fields = result["fields"]["rows"]
    assert [(r["name"], r["source"]) for r in fields] == [("c", "rgbd"), ("c", "mesh"), ("et", "rgbd"), ("et", "mesh")]
    assert all(r["train_seconds"] > 0 and math.isfinite(r["surface_error_mean_rel"]) for r in fields)

    reg = result["registration"]["rows"]
    assert [(r["scene"], r["object"], r["method"]) for r in reg] == [
        (scene, obj, m) for scene, obj in QUICK_PAIRS for m in METHODS]
    assert all(r["seconds"] > 0 and math.isfinite(r["rot_geodesic_rad"]) for r in reg)

    render = result["render"]["rows"]
    assert [r["renderer"] for r in render] == list(QUICK_RENDERERS)
    # The tiny captures are a quarter of the benchmark's 256 x 192.
    assert all((r["width"], r["height"], r["views"]) == (64, 48, 2) and r["seconds_per_frame"] > 0 for r in render)
    baked = render[QUICK_RENDERERS.index("baked")]
    assert math.isfinite(baked["psnr_vs_neural"]) and baked["bake_seconds"] > 0
    assert all(result[part]["seconds"] > 0 for part in ("fields", "registration", "render"))

    table = md.read_text()
    for heading in ("1 passed, 1 failed", "`tests.a::test_bad`", "regnf bench fields --quick",
                    "regnf bench registration --quick", "regnf bench render --quick"):
        assert heading in table


@pytest.mark.parametrize("report, problem", [("not xml <", "not a readable JUnit XML report"),
                                             ("<html></html>", "no <testsuite>")])
def test_a_bad_tests_report_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       report: str, problem: str) -> None:
    junit = tmp_path / "tests.xml"
    junit.write_text(report)
    out = tmp_path / "check.json"
    rc = main(["bench", "gpu-check", "--device", "cpu", "--size", "tiny", "--tests", str(junit),
               "--json", str(out), "--cache-dir", str(tmp_path / "cache")])
    err = capsys.readouterr().err
    assert rc == 1 and problem in err and str(junit) in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and not (tmp_path / "cache").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_a_gpu_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["bench", "gpu-check", "--device", "cuda", "--json", str(tmp_path / "check.json"),
               "--cache-dir", str(tmp_path / "cache")])
    err = capsys.readouterr().err
    assert rc == 1 and "--device cuda: CUDA is not available" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "cache").exists()
