"""Image sequences: animated GIFs and MP4 videos, written atomically, and as part of a render folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageSequence

import regnf.compositor.render_folder as RV
import regnf.compositor.sequence_io as SIO
from regnf.compositor import Camera
from regnf.compositor.cameras_io import OrbitConfig, orbit_around_bounds
from regnf.compositor.render_folder import RenderConfig, render_views
from regnf.compositor.sequence_io import SequenceBackendError, write_gif, write_mp4
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.file_lock import LOCK_NAME
from regnf.core.image_io import read_rgb_png

from . import golden_scenes as G


def frames(n: int, h: int = 18, w: int = 24) -> list[np.ndarray]:
    """Smooth colour ramps, a different one per frame."""
    v, u = np.mgrid[0:h, 0:w]
    return [np.stack([u * 255 // (w - 1), v * 255 // (h - 1), np.full_like(u, 40 * k)], -1).astype(np.uint8)
            for k in range(n)]


def read_gif(path: Path) -> tuple[list[np.ndarray], list[int], int | None]:
    """Frames (h, w, 3) uint8, durations in ms and the loop count of a GIF."""
    with Image.open(path) as im:
        loop = im.info.get("loop")
        pairs = [(np.asarray(f.convert("RGB")).copy(), f.info["duration"]) for f in ImageSequence.Iterator(im)]
    return [p[0] for p in pairs], [p[1] for p in pairs], loop


def test_gif_round_trip(tmp_path: Path) -> None:
    src = frames(5)
    assert write_gif(tmp_path / "a.gif", src, fps=10) == tmp_path / "a.gif"
    back, durations, loop = read_gif(tmp_path / "a.gif")
    assert len(back) == 5 and all(b.shape == (18, 24, 3) for b in back)
    assert durations == [100] * 5 and loop == 0  # 10 fps, looping forever
    err = np.abs(back[0].astype(int) - src[0].astype(int))
    assert err.mean() < 3.0 and err.max() <= 16  # 256-colour palette
    np.testing.assert_allclose([np.median(b[..., 2]) for b in back], [0, 40, 80, 120, 160], atol=4)  # in order
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif"]  # no temporary file left
    # Floats in [0, 1] are accepted; Pillow merges a repeated frame into one longer frame.
    write_gif(tmp_path / "b.gif", [src[1] / 255.0, src[1] / 255.0, src[2] / 255.0], fps=5)
    back, durations, _ = read_gif(tmp_path / "b.gif")
    assert len(back) == 2 and durations == [400, 200]


def test_a_failed_write_leaves_nothing_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    old = tmp_path / "old.gif"
    write_gif(old, frames(2))
    before = old.read_bytes()

    def failing(images, f, fps):
        f.write(b"GIF89a half a file")
        raise OSError("disk full")

    monkeypatch.setattr(SIO, "_encode_gif", failing)
    for dest in (old, tmp_path / "new.gif"):
        with pytest.raises(OSError, match="disk full"):
            write_gif(dest, frames(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.gif"] and old.read_bytes() == before


def test_bad_sequences_are_refused_before_writing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="at least one frame"):
        write_gif(tmp_path / "a.gif", [])
    with pytest.raises(ValueError, match="frame 1 is 20 x 18 pixels, frame 0 is 24 x 18"):
        write_gif(tmp_path / "a.gif", [frames(1)[0], frames(1, w=20)[0]])
    with pytest.raises(ValueError, match=r"frame 0: rgb must be \(h, w, 3\)"):
        write_gif(tmp_path / "a.gif", [np.zeros((4, 4), np.uint8)])
    with pytest.raises(ValueError, match="fps must be finite and > 0"):
        write_gif(tmp_path / "a.gif", frames(1), fps=0)
    with pytest.raises(ValueError, match="folder .*missing does not exist"):
        write_mp4(tmp_path / "missing" / "a.mp4", frames(1))
    assert not any(tmp_path.iterdir())


def test_mp4_without_its_package_says_which_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(SIO.importlib.util, "find_spec", lambda name: None)  # as if not installed
    with pytest.raises(SequenceBackendError, match="needs the package imageio-ffmpeg"):
        write_mp4(tmp_path / "a.mp4", frames(3))
    assert isinstance(SequenceBackendError("x"), ImportError)
    assert not any(tmp_path.iterdir())


def test_mp4_round_trip(tmp_path: Path) -> None:
    import imageio.v2 as imageio

    src = frames(4, h=17, w=23)  # odd sizes: the last row and column are repeated
    write_mp4(tmp_path / "a.mp4", src, fps=10)
    with imageio.get_reader(tmp_path / "a.mp4") as reader:
        back = [np.asarray(f) for f in reader]
    assert len(back) == 4 and back[0].shape == (18, 24, 3)
    assert np.abs(back[0][:17, :23].astype(int) - src[0].astype(int)).mean() < 8.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mp4"]


def cameras(n: int, width: int = 24, height: int = 18) -> list[Camera]:
    return orbit_around_bounds(np.array([[-1.6, -1.4, 0.0], [1.6, 1.4, 1.2]]),
                               OrbitConfig(n=n, width=width, height=height, radius=2.2, elevation_deg=35.0))


def test_render_views_writes_the_sequence_in_its_commit(tmp_path: Path) -> None:
    field = G.composite("own", StageCompositeConfig())
    out = tmp_path / "out"
    report = render_views(field, cameras(3), out, RenderConfig(sequence="gif", sequence_fps=4, progress=False))
    assert report.sequence == out / "sequence.gif"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{k}_{i:04d}.png" for k in ("rgb", "depth", "instance") for i in range(3)]
        + ["contact_sheet.png", "render.json", "sequence.gif", LOCK_NAME])  # no staging folder left
    files = json.loads((out / "render.json").read_text())["files"]
    assert files["sequence"] == "sequence.gif" and files["sequence_fps"] == 4
    back, durations, _ = read_gif(out / "sequence.gif")
    assert len(back) == 3 and durations == [250] * 3
    for k in range(3):
        assert np.abs(back[k].astype(int) - read_rgb_png(out / f"rgb_{k:04d}.png").astype(int)).mean() < 3.0
    # Overwriting without a sequence drops the old one with the old views.
    report = render_views(field, cameras(2), out, RenderConfig(progress=False, overwrite=True))
    assert report.sequence is None and not (out / "sequence.gif").exists()
    assert json.loads((out / "render.json").read_text())["files"]["sequence"] is None


def test_a_sequence_that_cannot_be_written_writes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    field = G.composite("own", StageCompositeConfig(mode="scene"))
    out = tmp_path / "out"
    gif = RenderConfig(sequence="gif", progress=False)
    with pytest.raises(ValueError, match="needs views of one size, the cameras have 24 x 16, 24 x 18"):
        render_views(field, cameras(1) + cameras(1, height=16), out, gif)
    if not SIO.mp4_available():
        with pytest.raises(SequenceBackendError, match="imageio-ffmpeg"):
            render_views(field, cameras(2), out, RenderConfig(sequence="mp4", progress=False))
    assert not out.exists()
    render_views(field, cameras(2), out, RenderConfig(progress=False))
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def failing(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(RV, "write_sequence", failing)
    with pytest.raises(OSError, match="disk full"):
        render_views(field, cameras(3), out, RenderConfig(sequence="gif", progress=False, overwrite=True))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # no staging folder, no new file
    with pytest.raises(ValueError, match="sequence must be one of"):
        RenderConfig(sequence="avi")  # type: ignore[arg-type]
