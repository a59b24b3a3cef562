"""What ``regnf inspect-capture`` reports, against the closed-form truth of test-written captures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regnf.captures.formats import read_capture
from regnf.captures.inspection import (
    depth_line,
    extent_line,
    frames_line,
    intrinsics_line,
    summarise_depth,
)
from tests.captures.ns_helpers import ROOM, true_depth, truth_poses, write_nerfstudio
from tests.captures.sphere_helpers import poses, sphere_depth, write_sphere_capture


def test_a_room_in_metres(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path / "ns")
    capture, _ = read_capture(tmp_path / "ns")
    summary = summarise_depth(capture)
    truth = np.concatenate([true_depth(p).ravel() for p in truth_poses()])
    # Every ray hits a wall; the depth is stored in millimetres.
    assert summary.valid_share == 1.0 and summary.frames_with_depth == 8
    np.testing.assert_allclose(summary.percentiles, np.percentile(truth, [1, 50, 99]), atol=1e-3)
    np.testing.assert_allclose(summary.extent, ROOM, atol=2e-3)
    assert frames_line(capture) == "8 (train 8, test 0)"
    assert intrinsics_line(capture) == "fx 20.0, fy 21.0, cx 19.5, cy 15.2 px; distortion none"
    assert depth_line(summary, 8) == ("p1 1.63 m, p50 2.58 m, p99 3.99 m; valid 100.0 % of the pixels "
                                      "(8 of 8 frames have depth)")
    assert extent_line(summary) == "6.00 x 5.00 x 3.00 m, from (1.00, -2.00, 0.00) to (7.00, 3.00, 3.00)"


def test_the_valid_share_counts_every_pixel(tmp_path: Path) -> None:
    capture = write_sphere_capture(tmp_path / "sphere")
    truth = np.stack([sphere_depth(p) for p in poses()])
    summary = summarise_depth(capture)
    assert summary.valid_share == float((truth > 0).mean())
    np.testing.assert_allclose(summary.percentiles, np.percentile(truth[truth > 0], [1, 50, 99]), atol=1e-5)


def test_frames_the_reader_skipped_are_counted(tmp_path: Path) -> None:
    capture = write_sphere_capture(tmp_path / "sphere")
    capture.meta["skipped_frames"] = 3
    assert frames_line(capture) == "12 (train 12, test 0), 3 skipped by the reader"
