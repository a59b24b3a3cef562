"""ScanNet export: poses, depth, skipped frames, frame order and resampled colour against the
analytic room written by test code; detection; the training data's fingerprint."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from regnf.captures.formats import detect_format, read_capture
from regnf.captures.model import Capture, CaptureError
from regnf.captures.resample import resample_to_grid
from regnf.synthetic.cache import Cache
from regnf.training.training import RGBDTrainConfig
from tests.captures.scannet_helpers import (
    BAD_FRAME,
    FACE_COLOURS,
    K_COLOUR,
    K_DEPTH,
    N_FRAMES,
    ROOM,
    H,
    W,
    colour_on_depth_grid,
    true_depth,
    write_matrix,
    write_scannet,
)


def _frame_ids(capture: Capture) -> list[int]:
    return [int(f.rgb_path.stem) for f in capture.frames]


def test_poses_depth_skipped_frame_order_and_up(tmp_path: Path) -> None:
    poses = write_scannet(tmp_path)
    capture, fmt = read_capture(tmp_path)
    assert fmt == "scannet" and (capture.width, capture.height) == (W, H)
    # Numerical order (0, 1, 2, ..., 10, 11), not the file system's nor the lexical (0, 1, 10, 11, 2).
    kept = [k for k in range(N_FRAMES) if k != BAD_FRAME]
    assert _frame_ids(capture) == kept
    assert capture.meta["skipped_frames"] == 1 and capture.meta["skipped_frame_ids"] == [BAD_FRAME]
    assert capture.meta["format"] == "scannet"
    np.testing.assert_array_equal(capture.up, [0.0, 0.0, 1.0])
    assert capture.poses_estimated and not capture.zero_depth_is_empty
    for i, k in enumerate(kept):
        np.testing.assert_allclose(capture.camtoworld_metres(i), poses[k], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(capture.frames[i].intrinsics, K_DEPTH)
        np.testing.assert_array_equal(capture.frames[i].rgb_intrinsics, K_COLOUR)
        metres = capture.depth(i).astype(np.float64) * capture.scale
        # Millimetre PNG: rounding to the millimetre, plus float32 arithmetic.
        np.testing.assert_allclose(metres, true_depth(poses[k]), rtol=0, atol=0.5e-3 + 1e-5)
    # The whole room lies inside the normalised unit box (no crop).
    s, c = capture.scale, capture.worldtogt[:3, 3]
    assert np.all(c - s <= ROOM[0]) and np.all(c + s >= ROOM[1])


def test_poses_written_with_six_decimals_are_rigid_enough(tmp_path: Path) -> None:
    """SensReader writes matrices with ``%f`` (6 decimals): the rounding is no shear or scale."""
    poses = write_scannet(tmp_path)
    for k in range(N_FRAMES):
        if k != BAD_FRAME:
            np.savetxt(tmp_path / "pose" / f"{k}.txt", poses[k], fmt="%f")
    capture, _ = read_capture(tmp_path)
    for i, k in enumerate(_frame_ids(capture)):
        np.testing.assert_allclose(capture.camtoworld_metres(i), poses[k], rtol=0, atol=1e-6)


@pytest.mark.parametrize(("ext", "window", "tol"), [(".png", 3, 1e-6), (".jpg", 5, 4 / 255)])
def test_colour_is_resampled_onto_the_depth_grid(tmp_path: Path, ext: str, window: int, tol: float) -> None:
    """Away from the walls' edges (every depth pixel within ``window // 2`` sees the same face)
    each depth pixel gets its wall's colour: exactly from a PNG, to JPEG's error from a JPEG."""
    poses = write_scannet(tmp_path, ext)
    capture, _ = read_capture(tmp_path)
    for i, k in enumerate(_frame_ids(capture)):
        expected, face = colour_on_depth_grid(poses[k])
        rgb = capture.rgb(i)
        assert rgb.shape == (H, W, 3) and rgb.dtype == np.float32
        inner = minimum_filter(face, window, mode="constant", cval=-1) == maximum_filter(face, window)
        assert inner.mean() > 0.7
        np.testing.assert_allclose(rgb[inner], expected[inner] / 255.0, rtol=0, atol=tol)
    assert len(np.unique(FACE_COLOURS, axis=0)) == 6


def test_resampling_reproduces_a_linear_image_exactly() -> None:
    """Bilinear sampling of a linear image is exact: the colour at a depth pixel is the linear
    function at that pixel centre's point K_src K_dst^-1 (u + 0.5, v + 0.5), pixel centres at +0.5."""
    h, w = 40, 50
    y, x = np.mgrid[0:h, 0:w] + 0.5
    a, b, c = 0.011, -0.007, 0.6
    image = np.stack([a * x + b * y + c, b * x, a * y], axis=-1).astype(np.float32)
    K_src = np.array([[60.0, 0.0, 24.0], [0.0, 58.0, 21.5], [0.0, 0.0, 1.0]])
    K_dst = np.array([[33.0, 0.0, 15.2], [0.0, 31.0, 11.9], [0.0, 0.0, 1.0]])
    out = resample_to_grid(image, K_src, K_dst, 22, 30)
    v, u = np.mgrid[0:22, 0:30] + 0.5
    xs = K_src[0, 0] * (u - K_dst[0, 2]) / K_dst[0, 0] + K_src[0, 2]
    ys = K_src[1, 1] * (v - K_dst[1, 2]) / K_dst[1, 1] + K_src[1, 2]
    inside = (xs >= 0.5) & (xs <= w - 0.5) & (ys >= 0.5) & (ys <= h - 0.5)
    assert inside.mean() > 0.8
    truth = np.stack([a * xs + b * ys + c, b * xs, a * ys], axis=-1)
    np.testing.assert_allclose(out[inside], truth[inside], rtol=0, atol=2e-6)
    # Beyond the image the nearest edge pixel's colour (clamped, never garbage).
    assert np.all((out >= image.min(axis=(0, 1)) - 1e-6) & (out <= image.max(axis=(0, 1)) + 1e-6))


def test_detection(tmp_path: Path) -> None:
    write_scannet(tmp_path / "scene")
    assert detect_format(tmp_path / "scene").name == "scannet"
    assert read_capture(tmp_path / "scene", "scannet")[1] == "scannet"
    with pytest.raises(CaptureError, match=r"intrinsic/intrinsic_depth\.txt \(scannet\)"):
        read_capture(tmp_path)
    with pytest.raises(CaptureError, match=r"intrinsic_depth\.txt: file not found \(is this a ScanNet export"):
        read_capture(tmp_path, "scannet")


def test_the_fingerprint_hashes_poses_and_intrinsics(tmp_path: Path) -> None:
    """A changed pose file (even a skipped frame's) or colour intrinsics file changes the
    training data's key; the same bytes under another spelling of the path do not."""
    write_scannet(tmp_path / "scene")
    cache = Cache(tmp_path / "cache", progress=False)
    config = dataclasses.replace(RGBDTrainConfig(), steps=1)

    def key() -> str:
        return cache.rgbd_entry(read_capture(tmp_path / "scene")[0], config)[1]

    first = key()
    assert cache.rgbd_entry(read_capture(tmp_path / "scene" / ".." / "scene")[0], config)[1] == first
    seen = {first}
    pose = np.loadtxt(tmp_path / "scene" / "pose" / "3.txt")
    pose[0, 3] += 1e-4
    write_matrix(tmp_path / "scene" / "pose" / "3.txt", pose)
    seen.add(key())
    (tmp_path / "scene" / "pose" / f"{BAD_FRAME}.txt").write_text("-inf -inf -inf -inf\n" * 4 + "\n")
    seen.add(key())
    K4 = np.eye(4)
    K4[:3, :3] = K_COLOUR + np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    write_matrix(tmp_path / "scene" / "intrinsic" / "intrinsic_color.txt", K4)
    seen.add(key())
    assert len(seen) == 4
