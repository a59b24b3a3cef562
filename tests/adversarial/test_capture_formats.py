"""Bad nerfstudio and ScanNet captures through ``regnf train --capture``: one line naming the file,
exit 1, nothing written; and a good one trains."""

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
from tests.captures.scannet_helpers import N_FRAMES, write_matrix, write_scannet
from tests.cli.cli_helpers import assert_fails, run_cli


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
    "OPENCV k4": (lambda c: _edit(c, lambda d: d["frames"][3].update(k1=0.12, k4=0.01)),
                  (r"transforms\.json: frames\[3\] has k1=0\.12, k4=0\.01 \(camera_model OPENCV\): OPENCV has no "
                   r"k4; set it to 0")),
    "fisheye p1": (lambda c: _edit(c, lambda d: d.update(camera_model="OPENCV_FISHEYE", p1=0.001)),
                   r"transforms\.json has p1=0\.001 \(camera_model OPENCV_FISHEYE\): OPENCV_FISHEYE has no p1"),
    "pinhole k1": (lambda c: _edit(c, lambda d: d.update(camera_model="PINHOLE", k1=0.1)),
                   r"transforms\.json has k1=0\.1 \(camera_model PINHOLE\): PINHOLE has no k1"),
    "folding lens": (lambda c: _edit(c, lambda d: d.update(k1=-0.12)),
                     (r"transforms\.json: OPENCV k1=-0\.12: the image \(corners at distorted normalised radius "
                      r"1\.256\) is not one-to-one: the lens model folds over 59\.1 degrees off axis")),
    "folding frame": (lambda c: _edit(c, lambda d: d["frames"][3].update(k1=0.12, k2=-0.1)),
                      r"transforms\.json: frames\[3\]: OPENCV k1=0\.12, k2=-0\.1: the image .* folds over"),
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
    assert_fails(capsys, ["train", "--capture", str(cap), "--training.steps", "1", "--cache-dir", str(tmp_path / "cache")],
                 pattern)
    assert changes(before, snapshot(tmp_path)) == []


def test_a_folder_of_no_format_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(tmp_path), "--cache-dir", str(tmp_path / "cache")],
                 r"not a capture folder: expected one of meta_data\.json \(sdfstudio\), transforms\.json")
    assert changes(before, snapshot(tmp_path)) == []


def test_a_nerfstudio_capture_trains_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_nerfstudio(tmp_path / "ns")
    code, err = run_cli(capsys, ["train", "--capture", str(tmp_path / "ns"), "--training.steps", "3",
                                 "--cache-dir", str(tmp_path / "cache")])
    assert code == 0, err
    assert "nerfstudio format, 8 frames" in err
    assert "preset: scene (cameras inside the observed space" in err
    assert list((tmp_path / "cache" / "fields").glob("ns-rgbd-*.safetensors"))


def test_a_distorted_nerfstudio_capture_trains_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Per-frame lenses of both kinds of view (with and without distortion) in one training stack.
    write_nerfstudio(tmp_path / "ns", extra={"k1": -0.05, "p2": 0.001})
    _edit(tmp_path / "ns", lambda d: d["frames"][3].update(k1=0.0, p2=0.0))
    # The object preset: the room preset's set-up is what the end-to-end test above runs.
    code, err = run_cli(capsys, ["train", "--capture", str(tmp_path / "ns"), "--training.steps", "3", "--preset", "object",
                                 "--cache-dir", str(tmp_path / "cache")])
    assert code == 0, err
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


def _scaled_pose(c: Path) -> None:
    write_matrix(c / "pose/2.txt", np.loadtxt(c / "pose/2.txt") @ np.diag([2.0, 2, 2, 1]))


def _all_poses_lost(c: Path) -> None:
    for k in range(N_FRAMES):
        write_matrix(c / f"pose/{k}.txt", np.full((4, 4), -np.inf))


SCANNET_CASES = {
    "8-bit depth": (lambda c: iio.imwrite(c / "depth/3.png", np.full((48, 64), 9, np.uint8)),
                    r"depth/3\.png: frame 3: depth PNG is 8-bit .*16-bit PNG"),
    "wrong unit": (lambda c: iio.imwrite(c / "depth/0.png", np.full((48, 64), 60000, np.uint16)),
                   r"depth/0\.png: frame 0: median depth 60 m is beyond 50 m read as millimetres: is the depth"),
    "non-rigid": (_scaled_pose, r"pose/2\.txt: must be rigid \(scale 1\), got scale 2"),
    "missing depth": (lambda c: (c / "depth/4.png").unlink(),
                      r"depth/4\.png: file not found \(colour frame 4\.png needs it\)"),
    "missing pose": (lambda c: (c / "pose/10.txt").unlink(),
                     r"pose/10\.txt: file not found \(colour frame 10\.png needs it\)"),
    "all poses invalid": (_all_poses_lost, r"pose: all 12 poses are invalid \(non-finite entries\); no frame to use"),
    "colour not an image": (lambda c: (c / "color/2.png").write_text("not an image"),
                            r"color/2\.png: frame 2: cannot read image"),
    "colour size": (lambda c: iio.imwrite(c / "color/7.png", np.zeros((96, 120, 3), np.uint8)),
                    r"color/7\.png: frame 6: colour image is 120x96 pixels, frame 0 \(0\.png\) is 128x96"),
    "pose not 4x4": (lambda c: (c / "pose/1.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n"),
                     r"pose/1\.txt: expected a 4x4 matrix of numbers"),
    "extrinsics": (lambda c: write_matrix(c / "intrinsic/extrinsic_depth.txt", np.diag([1.0, 1, 1, 1]) + np.eye(4, k=3) * 0.05),
                   r"extrinsic_depth\.txt: extrinsics other than the identity are not supported"),
    "bad intrinsics": (lambda c: write_matrix(c / "intrinsic/intrinsic_color.txt", np.diag([-5.0, 5, 1, 1])),
                       r"intrinsic_color\.txt: focal lengths must be > 0"),
}


@pytest.mark.parametrize("case", SCANNET_CASES)
def test_a_bad_scannet_capture_is_one_line_and_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       case: str) -> None:
    cap = tmp_path / "scene"
    write_scannet(cap)
    breaker, pattern = SCANNET_CASES[case]
    breaker(cap)
    before = snapshot(tmp_path)
    assert_fails(capsys, ["train", "--capture", str(cap), "--training.steps", "1", "--cache-dir", str(tmp_path / "cache")],
                 pattern)
    assert changes(before, snapshot(tmp_path)) == []


def test_a_scannet_capture_trains_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_scannet(tmp_path / "scene")
    code, err = run_cli(capsys, ["train", "--capture", str(tmp_path / "scene"), "--training.steps", "1", "--preset", "object",
                                 "--cache-dir", str(tmp_path / "cache")])
    assert code == 0, err
    assert f"scannet format, {N_FRAMES - 1} frames, 1 skipped by the reader" in err
    assert list((tmp_path / "cache" / "fields").glob("scene-rgbd-*.safetensors"))
