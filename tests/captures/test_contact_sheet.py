"""The contact sheet: evenly spaced frames, colour above depth, pixels without depth in their own colour."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from regnf.captures.contact_sheet import (
    GAP,
    LABEL_HEIGHT,
    SHEET_FRAMES,
    THUMB_WIDTH,
    UNKNOWN_COLOUR,
    colour_depth,
    sheet_frames,
    write_contact_sheet,
)
from tests.captures.sphere_helpers import H, W, write_sphere_capture


def test_depth_colours_never_take_the_unknown_colour() -> None:
    depth = np.linspace(0.0, 3.0, 300).reshape(10, 30)
    rgb = colour_depth(depth, 0.5, 2.5, depth.shape)
    unknown = (rgb == UNKNOWN_COLOUR).all(-1)
    assert (unknown == (depth == 0)).all()
    assert (colour_depth(None, 0.5, 2.5, (4, 5)) == UNKNOWN_COLOUR).all()


def test_at_most_the_limit_evenly_spaced(tmp_path: Path) -> None:
    capture = write_sphere_capture(tmp_path / "sphere")
    assert sheet_frames(capture) == list(range(12))
    capture.frames = capture.frames * 5  # 60 frames
    got = sheet_frames(capture)
    assert len(got) == SHEET_FRAMES and got[0] == 0 and got[-1] == 59


def test_the_sheet_shows_colour_above_depth(tmp_path: Path) -> None:
    capture = write_sphere_capture(tmp_path / "sphere")
    out = tmp_path / "sheets" / "sphere.png"
    write_contact_sheet(capture, out, near=0.8, far=1.0, frames=[0, 5])
    sheet = iio.imread(out)
    th = round(THUMB_WIDTH * H / W)
    assert sheet.shape == (2 * GAP + LABEL_HEIGHT + 2 * th, 2 * (THUMB_WIDTH + GAP) + GAP, 3)
    # Frame 5's depth thumbnail: the sphere in depth colours, the void around it unknown.
    depth = sheet[GAP + LABEL_HEIGHT + th: GAP + LABEL_HEIGHT + 2 * th, 2 * GAP + THUMB_WIDTH: 2 * GAP + 2 * THUMB_WIDTH]
    unknown = (depth == UNKNOWN_COLOUR).all(-1)
    assert unknown[0, 0] and unknown[-1, -1] and not unknown[th // 2, THUMB_WIDTH // 2]
    # Its colour thumbnail above holds the frame's colour, resized (no unknown colour there).
    colour = sheet[GAP + LABEL_HEIGHT: GAP + LABEL_HEIGHT + th, 2 * GAP + THUMB_WIDTH: 2 * GAP + 2 * THUMB_WIDTH]
    assert abs(float(colour.mean()) - 255 * float(capture.rgb(5).mean())) < 3.0
    assert [p.name for p in out.parent.iterdir()] == ["sphere.png"]  # no temporary file left
