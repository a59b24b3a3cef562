"""Refusals of ``regnf inspect-capture`` and of ``regnf train``'s frame options and memory check:
one line, exit 1, nothing written, and (for memory) no depth read."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from regnf.captures.model import Capture
from regnf.core import preflight
from regnf.observations.sample_memory import training_bytes
from tests.adversarial.disk import changes, snapshot
from tests.captures.sphere_helpers import N_VIEWS, H, W, write_sphere_capture
from tests.cli.cli_helpers import assert_fails


def test_inspect_a_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    line = assert_fails(capsys, ["inspect-capture", str(tmp_path / "nope")], "no such folder")
    assert line == (f"regnf inspect-capture: {tmp_path / 'nope'}: no such folder: expected one of meta_data.json "
                    "(sdfstudio), transforms.json (nerfstudio), intrinsic/intrinsic_depth.txt (scannet)")
    assert changes(before, snapshot(tmp_path)) == []


def test_inspect_never_writes_into_the_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    write_sphere_capture(tmp_path / "cap")
    before = snapshot(tmp_path)
    real = os.path.realpath(tmp_path / "cap")
    assert_fails(capsys, ["inspect-capture", str(tmp_path / "cap"), "--sheet", str(tmp_path / "cap" / "s.png")],
                 rf"^regnf inspect-capture: --sheet .*s\.png: lies inside the capture folder {real}; "
                 "regnf only reads a capture: give a --sheet outside it$")
    # Run from inside the capture folder, the default sheet (out/inspect/) would land in it too.
    monkeypatch.chdir(tmp_path / "cap")
    assert_fails(capsys, ["inspect-capture", "."], r"--sheet out/inspect/cap\.png: lies inside the capture folder")
    assert changes(before, snapshot(tmp_path)) == []


def test_training_larger_than_memory_is_refused_before_any_depth_is_read(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    capture = write_sphere_capture(tmp_path / "cap")
    before = snapshot(tmp_path)
    monkeypatch.setattr(preflight, "available_memory_bytes", lambda: 200 * 10**6)
    monkeypatch.setattr(Capture, "depth", lambda self, i: pytest.fail(f"depth of frame {i} read"))
    need = training_bytes(N_VIEWS, H, W, 1) / 1e9
    line = assert_fails(capsys, ["train", "--capture", str(tmp_path / "cap"), "--cache-dir", str(tmp_path / "cache")],
                        "needs about")
    assert line == (f"regnf train: {capture.root}: training {N_VIEWS} frames of {W}x{H} at pixel stride 1 needs "
                    f"about {need:.1f} GB, 0.2 GB is free; use --training.pixel-stride or --max-frames")
    assert changes(before, snapshot(tmp_path)) == []


@pytest.mark.parametrize("option,value,message", [
    ("--stride", "0", "--stride must be at least 1, got 0"),
    ("--max-frames", "0", "--max-frames must be at least 1, got 0"),
    ("--training.pixel-stride", "0", "RGBDTrainConfig.pixel_stride must be a whole number >= 1, got 0"),
])
def test_bad_frame_options_are_refused_before_the_capture_is_read(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        option: str, value: str, message: str) -> None:
    write_sphere_capture(tmp_path / "cap")
    before = snapshot(tmp_path)
    monkeypatch.setattr("regnf.cli.commands_fields.read_capture", lambda *a: pytest.fail("capture read"))
    line = assert_fails(capsys, ["train", "--capture", str(tmp_path / "cap"), option, value,
                                 "--cache-dir", str(tmp_path / "cache")], message)
    assert line == f"regnf train: {message}"
    assert changes(before, snapshot(tmp_path)) == []
