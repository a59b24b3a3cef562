"""``regnf inspect-capture``, and what ``regnf train`` decides and prints: frames, up, preset."""

from __future__ import annotations

import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.cli.app import main
from regnf.io.checkpoint import load_field
from regnf.synthetic.capture import RoomCaptureConfig, capture_room
from tests.adversarial.disk import changes, snapshot
from tests.captures.ns_helpers import write_nerfstudio
from tests.captures.sphere_helpers import write_sphere_capture


def inspect(capsys: pytest.CaptureFixture[str], *args: str) -> dict[str, str]:
    """``regnf inspect-capture ARGS``'s lines by their label (it must succeed)."""
    capsys.readouterr()
    assert main(["inspect-capture", *args]) == 0
    lines = capsys.readouterr().out.splitlines()
    return {line.split(":", 1)[0]: line.split(":", 1)[1].strip() for line in lines}


def test_inspect_a_room_of_ours(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                monkeypatch: pytest.MonkeyPatch) -> None:
    capture = capture_room("ac-room", tmp_path / "room", RoomCaptureConfig(width=32, height=24, n_views=6,
                                                                            progress=False))
    before = snapshot(tmp_path / "room")
    monkeypatch.chdir(tmp_path)
    got = inspect(capsys, str(tmp_path / "room"))
    assert got["format"] == "sdfstudio" and got["frames"] == "6 (train 6, test 0)"
    assert got["resolution"] == "32 x 24"
    assert got["up"] == "+Z (format convention)"
    assert got["poses"] == "exact" and got["zero depth"] == "the ray hit nothing (an ideal render)"
    assert got["preset"] == "scene (a room: the capture's metadata says kind 'scene')"
    assert got["depth"].endswith("valid 100.0 % of the pixels (6 of 6 frames have depth)")
    # Inside the room's true mesh, in metres (its walls and floor bound the depth).
    corners = re.search(r"from \((.*)\) to \((.*)\)$", got["extent"]).groups()
    lo, hi = (np.array([float(v) for v in c.split(",")]) for c in corners)
    bounds = capture.gt_mesh().bounds
    assert (lo >= bounds[0] - 0.01).all() and (hi <= bounds[1] + 0.01).all() and (hi - lo).min() > 1.0
    sheet = tmp_path / "out" / "inspect" / "room.png"
    assert got["sheet"] == "out/inspect/room.png" and iio.imread(sheet).shape[2] == 3
    assert changes(before, snapshot(tmp_path / "room")) == []


def test_inspect_a_nerfstudio_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_nerfstudio(tmp_path / "ns")
    got = inspect(capsys, str(tmp_path / "ns"), "--sheet", str(tmp_path / "ns.png"))
    assert got["format"] == "nerfstudio" and got["frames"] == "8 (train 8, test 0)"
    assert got["intrinsics"] == "fx 20.0, fy 21.0, cx 19.5, cy 15.2 px; distortion none"
    assert got["extent"] == "6.00 x 5.00 x 3.00 m, from (1.00, -2.00, 0.00) to (7.00, 3.00, 3.00)"
    assert got["up"].endswith("), estimated from the floor plane")
    assert got["poses"].startswith("estimates") and got["zero depth"] == "unknown (no sensor return)"
    assert got["preset"] == ("scene (cameras inside the observed space: 8 of 8 camera centres inside the box of "
                             "the depth points)")
    assert (tmp_path / "ns.png").is_file()


def test_train_selects_frames_and_says_its_up_and_preset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = write_sphere_capture(tmp_path / "sphere")
    out = tmp_path / "f.safetensors"
    capsys.readouterr()
    assert main(["train", "--capture", str(capture.root), "--stride", "3", "--training.pixel-stride", "2", "--training.steps", "2",
                 "--cache-dir", str(tmp_path / "cache"), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "frames: 4 of 12 training frames" in err
    assert "up: (" in err and "estimated from the cameras' mean up vector (no floor plane found)" in err
    assert "preset: object (cameras outside the observed space, looking in: 0 of 12 camera centres" in err
    provenance = load_field(out).info.provenance
    assert provenance["train_indices"] == [0, 3, 6, 9] and provenance["train_frames"] == 4
    assert provenance["train_config"]["pixel_stride"] == 2
    assert len(provenance["up"]) == 3 and provenance["up"][2] > 0.99
    # Every frame, the same up: another field; given again: the same one.
    assert main(["train", "--capture", str(capture.root), "--max-frames", "4", "--stride", "3", "--training.pixel-stride", "2",
                 "--training.steps", "2", "--cache-dir", str(tmp_path / "cache")]) == 0
    assert len(list((tmp_path / "cache" / "fields").glob("*.safetensors"))) == 1
    assert main(["train", "--capture", str(capture.root), "--training.pixel-stride", "2", "--training.steps", "2", "--up", "+z",
                 "--cache-dir", str(tmp_path / "cache"), "--out", str(out)]) == 0
    assert "up: +Z (given by --up)" in capsys.readouterr().err
    assert len(list((tmp_path / "cache" / "fields").glob("*.safetensors"))) == 2
    assert load_field(out).info.provenance["up"] == [0.0, 0.0, 1.0]
