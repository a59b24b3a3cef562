"""The training cache: keyed by the bytes of every input file whatever the path's spelling,
and never handing out a damaged entry."""

from __future__ import annotations

import functools
import os
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.io.checkpoint import verify_checkpoint
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.synthetic import cache as cache_module
from regnf.synthetic.cache import Cache
from regnf.training.training import RGBDTrainConfig
from tests.observations import capture_helpers as C

TINY = NeuralSDFConfig(levels=2, finest_resolution=16, hidden_dim=16, base_resolution=8,
                       geo_feature_dim=3, color_hidden_dim=8)
"""As tests/scene_graph/helpers.py."""

CONFIG = RGBDTrainConfig(steps=2, batch_surface=256, batch_free=128, batch_empty=128,
                         batch_eikonal=64, architecture=TINY)
"""Two steps: what matters is whether training runs, not what it makes."""


VIEWS = 6
"""Frames per capture (enough depth pixels to train on, quick to sphere-trace)."""


@functools.lru_cache(maxsize=1)
def views() -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Colour (uint8), depth in metres and metre poses of the first VIEWS analytic views."""
    field, poses = C.analytic_object(), C.camera_poses()[:VIEWS]
    rgbs, depths = [], []
    for c2w in poses:
        out = render(field, Camera(C.K, C.WIDTH, C.HEIGHT, c2w), C.TRACE)  # to_world = I
        rgbs.append(np.round(out.rgb.numpy() * 255.0).astype(np.uint8))
        depths.append(out.depth.numpy().astype(np.float64) * C.WORLD_SCALE)
    return rgbs, depths, C.poses_in_metres(poses)


@pytest.fixture
def two_captures(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path]:
    """Captures ``a`` and ``b`` in the working directory: the same meta_data.json byte for
    byte, other images and depths."""
    a = tmp_path / "a"
    rgbs, depths, poses = views()
    write_capture(a, rgbs, depths, poses, C.K, C.WORLDTOGT)
    b = tmp_path / "b"
    shutil.copytree(a, b)
    for name in ("000001_depth.npy", "000002_depth.npy"):
        depth = np.load(b / name)
        np.save(b / name, np.where(depth > 0, depth * np.float32(1.05), depth), allow_pickle=False)
    rgb = iio.imread(b / "000003_rgb.png")
    iio.imwrite(b / "000003_rgb.png", 255 - rgb)
    assert (a / "meta_data.json").read_bytes() == (b / "meta_data.json").read_bytes()
    monkeypatch.chdir(tmp_path)
    return a, b


@pytest.fixture
def trainings(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The capture roots the cache trains on, in order (training itself still runs)."""
    calls: list[str] = []
    train = cache_module.train_rgbd

    def counting(capture, *args, **kwargs):
        calls.append(str(capture.root))
        return train(capture, *args, **kwargs)

    monkeypatch.setattr(cache_module, "train_rgbd", counting)
    return calls


def test_the_key_covers_every_file_whatever_the_path(two_captures: tuple[Path, Path], tmp_path: Path) -> None:
    a, _ = two_captures
    cache = Cache(tmp_path / "cache", progress=False)
    os.symlink(a, tmp_path / "link")
    keys = {
        spelling: cache.rgbd_entry(load_capture(spelling), CONFIG)[0]
        for spelling in ("a", "./a", str(a), "link", "a/meta_data.json", "a/../a")
    }
    assert len(set(keys.values())) == 1, keys
    assert cache.rgbd_entry(load_capture("b"), CONFIG)[0] != keys["a"]


def test_a_new_training_version_keys_the_fields_anew(
    two_captures: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A changed default is not in the key (only non-default settings are): the version is.
    # (``two_captures`` made the capture ``a`` in the working directory.)
    cache = Cache(tmp_path / "cache", progress=False)
    before = cache.rgbd_entry(load_capture("a"), CONFIG)[0]
    monkeypatch.setattr(cache_module, "TRAIN_VERSION", cache_module.TRAIN_VERSION + 1)
    assert cache.rgbd_entry(load_capture("a"), CONFIG)[0] != before


def test_other_images_under_the_same_metadata_are_trained_anew(
    two_captures: tuple[Path, Path], tmp_path: Path, trainings: list[str]
) -> None:
    a, b = two_captures
    cache = Cache(tmp_path / "cache", progress=False)
    field_a = cache.rgbd_field(load_capture("a"), CONFIG)
    assert cache.rgbd_field(load_capture(str(a)), CONFIG) == field_a  # reused, not retrained
    assert len(trainings) == 1
    field_b = cache.rgbd_field(load_capture("b"), CONFIG)
    assert len(trainings) == 2 and trainings[1] == str(b)
    assert field_b != field_a and field_b.read_bytes() != field_a.read_bytes()
    assert verify_checkpoint(field_b)["provenance"]["capture"] == str(b)


@pytest.mark.parametrize("damage", ["flipped-bit", "truncated", "empty", "other-field"])
def test_a_damaged_entry_is_remade_not_returned(
    two_captures: tuple[Path, Path], tmp_path: Path, trainings: list[str], damage: str
) -> None:
    cache = Cache(tmp_path / "cache", progress=False)
    path = cache.rgbd_field(load_capture("a"), CONFIG)
    good = path.read_bytes()
    if damage == "flipped-bit":
        data = bytearray(good)
        data[-9] ^= 0x01  # a low bit near the end of the tensor data: still a finite number
        path.write_bytes(bytes(data))
    elif damage == "truncated":
        path.write_bytes(good[: len(good) * 2 // 3])
    elif damage == "empty":
        path.write_bytes(b"")
    else:  # an intact checkpoint, but trained on b, under a's name
        shutil.copyfile(cache.rgbd_field(load_capture("b"), CONFIG), path)
    damaged = path.read_bytes()
    remade = cache.rgbd_field(load_capture("a"), CONFIG)
    assert remade == path
    assert trainings[-1] == str(tmp_path / "a")  # trained again
    assert path.read_bytes() != damaged
    verify_checkpoint(path)
    leftovers = [p.name for p in path.parent.iterdir() if p != path and "-rgbd-" not in p.name]
    assert leftovers == []  # remade atomically: no temporary file left
