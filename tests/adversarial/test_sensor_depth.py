"""Bad sensor-depth inputs through ``regnf train --capture``: a bad ``regnf.depth_noise`` and bad
depth confidence maps are one line naming the file, exit 1, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.captures.sdfstudio import write_capture
from tests.adversarial.disk import changes, snapshot
from tests.captures.ns_helpers import H, W, write_nerfstudio
from tests.cli.cli_helpers import assert_fails


@pytest.mark.parametrize(
    ("model", "pattern"),
    [
        ({"constant_m": -0.001}, r"sd/meta_data\.json: regnf\.depth_noise: constant_m must be > 0 and quadratic_per_m"),
        ("kinect", r"sd/meta_data\.json: regnf\.depth_noise must be 'none' or an object of model fields, got 'kinect'"),
        ({"sigma_m": 0.01}, r"sd/meta_data\.json: regnf\.depth_noise has unknown field\(s\) 'sigma_m'; known: constant_m"),
    ],
)
def test_a_bad_depth_noise_model_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             model: object, pattern: str) -> None:
    write_capture(tmp_path / "sd", [np.zeros((6, 8, 3), np.uint8)], [np.full((6, 8), 1.5)], np.eye(4)[None],
                  np.diag([5.0, 5.0, 1.0]), np.eye(4), meta={"depth_noise": model})
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(tmp_path / "sd"), "--training.steps", "1",
                          "--cache-dir", str(tmp_path / "cache")], pattern)
    assert changes(before, snapshot(tmp_path)) == []


@pytest.mark.parametrize(
    ("image", "pattern"),
    [
        (np.full((H + 2, W), 2, np.uint8), r"confidence/1\.png: frame 1: depth confidence shape \(32, 40\) does not match the depth's 30x40"),
        (np.full((H, W), 255, np.uint8), r"confidence/1\.png: frame 1: depth confidence has values up to 255; expected 0 \(low\), 1 \(medium\) or 2 \(high\)"),
        (np.full((H, W), 2, np.uint16), r"confidence/1\.png: frame 1: depth confidence has dtype uint16, expected uint8"),
    ],
)
def test_a_bad_confidence_map_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                          image: np.ndarray, pattern: str) -> None:
    cap = tmp_path / "ns"
    data = write_nerfstudio(cap)
    (cap / "confidence").mkdir()
    for i, frame in enumerate(data["frames"]):
        iio.imwrite(cap / "confidence" / f"{i}.png", image if i == 1 else np.full((H, W), 2, np.uint8))
        frame["confidence_path"] = f"confidence/{i}.png"
    (cap / "transforms.json").write_text(json.dumps(data))
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(cap), "--training.steps", "1", "--cache-dir", str(tmp_path / "cache")],
                 pattern)
    assert changes(before, snapshot(tmp_path)) == []
