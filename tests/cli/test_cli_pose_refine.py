"""``regnf train --pose-refine``: what it prints, and which settings share a cached field."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from regnf.captures.sdfstudio import write_capture
from regnf.io.checkpoint import read_header
from tests.cli.cli_helpers import run_cli
from tests.training.test_pose_refinement import (
    OFFSET,
    SCALE,
    H,
    K,
    W,
    raycast_depth,
    true_poses_m,
)

REPORT = re.compile(r"pose refinement: median ([\d.]+) cm / ([\d.]+) deg, worst ([\d.]+) cm / "
                    r"([\d.]+) deg over (\d+) frames")


def _write(root: Path, poses: str) -> Path:
    """The analytic room of the pose refinement tests (12 frames of 40 x 30), poses marked ``poses``."""
    c2w = true_poses_m()
    worldtogt = np.diag([SCALE, SCALE, SCALE, 1.0])
    worldtogt[:3, 3] = OFFSET
    rgbs = [np.full((H, W, 3), 128, np.uint8)] * len(c2w)
    write_capture(root, rgbs, [raycast_depth(c) for c in c2w], c2w, K, worldtogt, meta={"poses": poses})
    return root


def _fields(cache: Path) -> set[Path]:
    return set((cache / "fields").glob("*.safetensors"))


def test_train_reports_the_pose_corrections(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    exact = _write(tmp_path / "exact", "exact")
    estimated = _write(tmp_path / "estimated", "estimated")
    cache = tmp_path / "cache"
    base = ["train", "--preset", "object", "--training.steps", "4", "--cache-dir", str(cache)]

    # Exact poses: no refinement, and the key of a config that has none.
    status, err = run_cli(capsys, [*base, "--capture", str(exact)])
    assert status == 0 and "pose refinement: off (poses exact)" in err
    exact_fields = _fields(cache)
    status, err = run_cli(capsys, [*base, "--capture", str(exact), "--pose-refine", "off"])
    assert status == 0 and "pose refinement: off (--pose-refine off)" in err
    assert _fields(cache) == exact_fields  # the same field, reused

    # Estimated poses: refined by default; the line is what the field records.
    status, err = run_cli(capsys, [*base, "--capture", str(estimated)])
    assert status == 0
    found = REPORT.search(err)
    assert found, err
    (path,) = _fields(cache) - exact_fields
    recorded = read_header(path)["provenance"]["pose_refinement"]
    assert int(found[5]) == recorded["frames"] == 12
    assert float(found[3]) == pytest.approx(recorded["worst_cm"], abs=0.05)
    assert float(found[4]) == pytest.approx(recorded["worst_deg"], abs=0.005)
    assert recorded["worst_cm"] > 0  # four steps moved the poses
    # "on" is what "auto" did there: the same field; "off" is another.
    status, err = run_cli(capsys, [*base, "--capture", str(estimated), "--pose-refine", "on"])
    assert status == 0 and REPORT.search(err) and len(_fields(cache)) == 2
    status, err = run_cli(capsys, [*base, "--capture", str(estimated), "--pose-refine", "off"])
    assert status == 0 and "pose refinement: off (--pose-refine off)" in err and len(_fields(cache)) == 3
