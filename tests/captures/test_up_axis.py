"""The up of a capture: the format's convention, the floor plane, the cameras' mean up; ``--up`` values."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from regnf.captures.formats import read_capture
from regnf.captures.model import Capture
from regnf.captures.up_axis import (
    UP_CHOICES,
    UpEstimate,
    estimate_up,
    parse_up,
    resolve_up,
    up_line,
)
from regnf.synthetic.capture import ObjectCaptureConfig, capture_object
from tests.captures.ns_helpers import write_nerfstudio
from tests.captures.sphere_helpers import CENTRE, poses, write_sphere_capture


def rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def turned(capture: Capture, R: np.ndarray) -> Capture:
    """``capture`` with its metric world turned by ``R`` (the frames' poses and depth unchanged)."""
    M = np.eye(4)
    M[:3, :3] = R
    capture.worldtogt = M @ capture.worldtogt
    return capture


@pytest.mark.parametrize("text,axis", [("+x", (1, 0, 0)), ("-y", (0, -1, 0)), ("z", (0, 0, 1)), ("+Z", (0, 0, 1)),
                                       ("-z", (0, 0, -1))])
def test_parse_up_names_an_axis(text: str, axis: tuple[int, int, int]) -> None:
    assert parse_up(text).tolist() == list(map(float, axis))


def test_parse_up_auto_and_bad_values() -> None:
    assert parse_up("auto") is None
    assert set(UP_CHOICES) >= {"auto", "+x", "-x", "+y", "-y", "+z", "-z", "z"}
    with pytest.raises(ValueError, match="--up up: expected one of auto"):
        parse_up("up")


def test_the_format_convention_wins_without_reading_depth(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    capture = capture_object("c", tmp_path / "c", ObjectCaptureConfig(width=24, height=24, n_views=4, progress=False))
    monkeypatch.setattr(Capture, "depth", lambda self, i: pytest.fail("depth read"))
    up = estimate_up(capture)
    assert up.source == "format" and up.direction.tolist() == [0.0, 0.0, 1.0]
    assert up_line(up) == "up: +Z (format convention)"


def test_the_floor_plane_of_a_room_in_metres(tmp_path: Path) -> None:
    # The test-written room's floor is z = 0 (ns_helpers.ROOM); the format states no up.
    write_nerfstudio(tmp_path / "ns")
    capture, _ = read_capture(tmp_path / "ns")
    assert capture.up is None
    up = estimate_up(capture)
    assert up.source == "floor"
    assert np.degrees(np.arccos(up.direction[2])) < 0.2  # millimetre depth: a small tilt
    assert up_line(up).startswith("up: (") and up_line(up).endswith("), estimated from the floor plane")


def test_the_floor_plane_follows_a_turned_world(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path / "ns")
    R = rotation_x(0.5)
    up = estimate_up(turned(read_capture(tmp_path / "ns")[0], R))
    assert up.source == "floor"
    assert np.degrees(np.arccos(np.clip(up.direction @ R[:, 2], -1, 1))) < 0.2


def test_without_a_floor_below_the_cameras_the_cameras_mean_up(tmp_path: Path) -> None:
    # An object seen from all around, some views from below its lowest face: no plane lies
    # below every camera, so the up is the cameras' mean up vector.
    capture = write_sphere_capture(tmp_path / "obj")
    assert capture.up is None
    up = estimate_up(capture)
    assert up.source == "cameras"
    # Truth, in closed form: each camera looks at the origin with +Z as up (look_at), so its up
    # vector is +Z made perpendicular to its view direction f = -eye / |eye|.
    f = CENTRE - poses()[:, :3, 3]
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    ups = np.array([0.0, 0.0, 1.0]) - f[:, 2:3] * f
    mean = (ups / np.linalg.norm(ups, axis=1, keepdims=True)).mean(axis=0)
    np.testing.assert_allclose(up.direction, mean / np.linalg.norm(mean), atol=1e-9)
    assert "cameras' mean up vector" in up_line(up)


def test_an_explicit_up_wins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_nerfstudio(tmp_path / "ns")
    capture, _ = read_capture(tmp_path / "ns")
    monkeypatch.setattr(Capture, "depth", lambda self, i: pytest.fail("depth read"))
    up = resolve_up(capture, "-y")
    assert up == UpEstimate(up.direction, "option", "given by --up") and up.direction.tolist() == [0.0, -1.0, 0.0]
    assert up_line(up) == "up: -Y (given by --up)"
