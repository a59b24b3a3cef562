"""Bad nerfstudio captures through ``regnf train --capture``: one line naming the file, exit 1,
nothing written; and a good one trains."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.captures.sdfstudio import write_capture
from tests.adversarial.disk import changes, snapshot
from tests.captures.ns_helpers import write_nerfstudio
from tests.regnf.cli_helpers import assert_fails, run_cli


def _edit(cap: Path, change: Callable[[dict], None]) -> None:
    data = json.loads((cap / "transforms.json").read_text())
    change(data)
    (cap / "transforms.json").write_text(json.dumps(data))


def _scale_pose(d: dict) -> None:
    d["frames"][0]["transform_matrix"] = (np.asarray(d["frames"][0]["transform_matrix"]) @ np.diag([2.0, 2, 2, 1])).tolist()


CASES = {
    "8-bit depth": (lambda c: iio.imwrite(c / "depth/frame_00001.png", np.full((30, 40), 9, np.uint8)),
                    r"depth/frame_00001\.png: frame 1: depth PNG is 8-bit .*16-bit PNG"),
    "wrong unit": (lambda c: _edit(c, lambda d: d.update(depth_unit_scale_factor=1.0)),
                   r"frame_00000\.png: frame 0: median depth .* beyond 50 m .*is the depth_unit_scale_factor right\?"),
    "non-rigid": (lambda c: _edit(c, _scale_pose), r"transforms\.json: frames\[0\]\.transform_matrix: .*rigid"),
    "missing image": (lambda c: (c / "images/frame_00002.png").unlink(),
                      r"transforms\.json: frames\[2\]\.file_path: file .*frame_00002\.png not found"),
    "camera model": (lambda c: _edit(c, lambda d: d.update(camera_model="EQUIRECTANGULAR")),
                     r"transforms\.json: unknown camera_model 'EQUIRECTANGULAR'; supported: PINHOLE"),
    "distortion": (lambda c: _edit(c, lambda d: d["frames"][3].update(k1=0.12)),
                   r"transforms\.json: frames\[3\] has k1=0\.12 \(camera_model OPENCV\): distortion is not supported yet"),
    "global distortion": (lambda c: _edit(c, lambda d: d.update(k1=-0.05, p2=0.001)),
                          r"transforms\.json has k1=-0\.05, p2=0\.001 \(camera_model OPENCV\): distortion is not"),
    "image size": (lambda c: _edit(c, lambda d: d.update(w=41)),
                   r"frame_00000\.png: frame 0: image is 40x30 pixels, the metadata says w x h = 41x30"),
}


@pytest.mark.parametrize("case", CASES)
def test_a_bad_nerfstudio_capture_is_one_line_and_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          case: str) -> None:
    cap = tmp_path / "ns"
    write_nerfstudio(cap)
    breaker, pattern = CASES[case]
    breaker(cap)
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(cap), "--steps", "1", "--cache-dir", str(tmp_path / "cache")],
                 pattern)
    assert changes(before, snapshot(tmp_path)) == []


def test_a_folder_of_no_format_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(tmp_path), "--cache-dir", str(tmp_path / "cache")],
                 r"not a capture folder: expected one of meta_data\.json \(sdfstudio\), transforms\.json")
    assert changes(before, snapshot(tmp_path)) == []


def test_a_nerfstudio_capture_trains_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_nerfstudio(tmp_path / "ns")
    code, err = run_cli(capsys, ["train", "--capture", str(tmp_path / "ns"), "--steps", "3",
                                 "--cache-dir", str(tmp_path / "cache")])
    assert code == 0, err
    assert "nerfstudio format, 8 frames" in err
    assert list((tmp_path / "cache" / "fields").glob("ns-rgbd-*.safetensors"))


def test_an_sdfstudio_depth_png_is_refused_not_unpickled(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # meta_data.json states no depth unit, so a PNG's integer counts have no meaning there.
    cap = tmp_path / "sd"
    depth = [np.full((6, 8), 1.5)]
    write_capture(cap, [np.zeros((6, 8, 3), np.uint8)], depth, np.eye(4)[None], np.diag([5.0, 5.0, 1.0]), np.eye(4))
    iio.imwrite(cap / "d.png", np.full((6, 8), 1500, np.uint16))
    data = json.loads((cap / "meta_data.json").read_text())
    data["frames"][0]["sensor_depth_path"] = "d.png"
    (cap / "meta_data.json").write_text(json.dumps(data))
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(cap), "--cache-dir", str(tmp_path / "cache")],
                 r"meta_data\.json: frames\[0\]\.sensor_depth_path: 'd\.png' is a PNG, but meta_data\.json "
                 r"states no depth unit")
    assert changes(before, snapshot(tmp_path)) == []
