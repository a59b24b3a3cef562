"""PNG output: formats, round trips and atomic writes."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import regnf.core.image_io as io
from regnf.core.image_io import (
    read_depth_png,
    read_instance_png,
    read_rgb_png,
    write_depth_png,
    write_instance_png,
    write_rgb_png,
)


def test_rgb_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.0, 1.0, size=(12, 16, 3))
    write_rgb_png(tmp_path / "c.png", torch.as_tensor(rgb, dtype=torch.float32))
    back = read_rgb_png(tmp_path / "c.png")
    assert back.dtype == np.uint8 and back.shape == (12, 16, 3)
    assert int(np.abs(back.astype(int) - np.round(rgb * 255).astype(int)).max()) <= 1
    with pytest.raises(ValueError, match=r"\(h, w, 3\)"):
        write_rgb_png(tmp_path / "bad.png", np.zeros((4, 4)))


def test_depth_is_16_bit_millimetres_with_zero_for_no_hit(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.3, 12.0, size=(10, 14))
    mask = rng.uniform(size=depth.shape) > 0.3
    depth[0, 0] = np.inf  # a miss written as inf
    path = write_depth_png(tmp_path / "d.png", depth, mask)
    with Image.open(path) as im:
        raw = np.asarray(im)
    assert raw.dtype == np.uint16
    back = read_depth_png(path)
    hit = mask & np.isfinite(depth)
    assert np.abs(back[hit] - depth[hit]).max() <= 0.0005 + 1e-12  # rounded to the mm
    assert bool((back[~hit] == 0).all())
    # A hit closer than half a millimetre must not read back as "no hit".
    write_depth_png(tmp_path / "near.png", np.array([[0.0002, 0.0]]))
    assert read_depth_png(tmp_path / "near.png").tolist() == [[0.001, 0.0]]
    with pytest.raises(ValueError, match="65.535"):
        write_depth_png(tmp_path / "far.png", np.array([[70.0]]))
    with pytest.raises(ValueError, match=">= 0"):
        write_depth_png(tmp_path / "neg.png", np.array([[-1.0]]))
    assert not (tmp_path / "far.png").exists() and not (tmp_path / "neg.png").exists()


def test_instance_ids_round_trip(tmp_path: Path) -> None:
    ids = torch.tensor([[-1, 0, 7], [3, -1, 65535]])
    write_instance_png(tmp_path / "i.png", ids)
    # No hit (-1) and the scene (0) are both the background, 0; instances keep their ids.
    assert read_instance_png(tmp_path / "i.png").tolist() == [[0, 0, 7], [3, 0, 65535]]
    with Image.open(tmp_path / "i.png") as im:  # read back without regnf's reader
        assert im.mode.startswith("I") and np.asarray(im).tolist() == [[0, 0, 7], [3, 0, 65535]]
    with pytest.raises(ValueError, match="integer"):
        write_instance_png(tmp_path / "f.png", np.zeros((2, 2), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\[-1, 65535\]"):
        write_instance_png(tmp_path / "o.png", np.array([[-2]]))


def test_a_failed_write_leaves_nothing_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "depth.png"
    write_depth_png(target, np.full((4, 4), 2.0))
    before = target.read_bytes()

    def broken(image, f) -> None:
        f.write(b"\x89PNG partial")  # half a file, then the encoder dies
        raise OSError("disk full")

    monkeypatch.setattr(io, "_encode", broken)
    with pytest.raises(OSError, match="disk full"):
        write_depth_png(target, np.full((4, 4), 3.0))
    with pytest.raises(OSError, match="disk full"):
        write_rgb_png(tmp_path / "new.png", np.zeros((4, 4, 3)))
    # The old file is intact, the new one never appeared, no temporary file remains.
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.png"]


def test_missing_folder_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        write_rgb_png(tmp_path / "nope" / "c.png", np.zeros((2, 2, 3)))


def test_written_images_get_the_usual_permissions(tmp_path: Path) -> None:
    mask = os.umask(0o022)
    try:
        p = write_rgb_png(tmp_path / "a.png", np.zeros((2, 2, 3), dtype=np.uint8))
    finally:
        os.umask(mask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644  # not mkstemp's private 0600
