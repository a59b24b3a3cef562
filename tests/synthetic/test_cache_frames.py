"""Cache keys of RGB-D fields with a frame selection and an up: a subset of frames is another
field; the up is recorded, and the keys of every-frame fields of regnf's captures stay as they were."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from regnf.captures.model import Capture
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.io.checkpoint import load_field
from regnf.observations.capture_fingerprint import capture_fingerprint
from regnf.synthetic.cache import Cache, capture_files, capture_info, config_key, entry_stem
from regnf.synthetic.capture import ObjectCaptureConfig, capture_object
from regnf.training.training import TRAIN_VERSION, RGBDTrainConfig
from tests.captures.sphere_helpers import write_sphere_capture

TINY = RGBDTrainConfig(steps=2, visibility_resolution=8, architecture=NeuralSDFConfig(
    levels=2, finest_resolution=16, hidden_dim=16, base_resolution=8, geo_feature_dim=3, color_hidden_dim=8))


@pytest.fixture(scope="module")
def ours(tmp_path_factory: pytest.TempPathFactory) -> Capture:
    """A capture of regnf's own renderer: ideal depth, +Z up by its format."""
    return capture_object("c", tmp_path_factory.mktemp("c") / "c",
                          ObjectCaptureConfig(width=24, height=24, n_views=6, progress=False))


def test_every_frame_and_the_formats_up_keep_todays_key(ours: Capture, tmp_path: Path) -> None:
    cache = Cache(tmp_path, progress=False)
    # The key as it was computed before selections and ups existed, by hand.
    fingerprint = capture_fingerprint(ours.root, capture_files(ours), ours.meta_name)
    stem = entry_stem(capture_info(ours).name, "capture")
    before = tmp_path / "fields" / f"{stem}-rgbd-{config_key(TINY, fingerprint, TRAIN_VERSION)}.safetensors"
    assert cache.rgbd_entry(ours, TINY)[0] == before
    assert cache.rgbd_entry(ours, TINY, ours.train_indices(), ours.up)[0] == before
    assert cache.rgbd_entry(ours, TINY, ours.train_indices(), [0.0, 0.0, 1.0])[0] == before


def test_a_subset_of_frames_or_another_up_is_another_field(ours: Capture, tmp_path: Path) -> None:
    cache = Cache(tmp_path, progress=False)
    every = cache.rgbd_entry(ours, TINY)[0]
    train = ours.train_indices()
    half = cache.rgbd_entry(ours, TINY, train[::2])[0]
    assert len({every, half, cache.rgbd_entry(ours, TINY, train[1::2])[0],
                cache.rgbd_entry(ours, TINY, None, [0.0, 1.0, 0.0])[0]}) == 4


def test_a_field_records_its_frames_and_its_up(tmp_path: Path) -> None:
    capture = write_sphere_capture(tmp_path / "sphere")
    assert capture.up is None  # no up by format: the one given is part of the key
    cache = Cache(tmp_path / "cache", progress=False)
    frames = capture.train_indices()[::3]
    up = np.array([0.1, 0.0, 0.99]) / np.linalg.norm([0.1, 0.0, 0.99])
    path = cache.rgbd_field(capture, TINY, frames, up)
    provenance = load_field(path).info.provenance
    assert provenance["train_indices"] == frames and provenance["train_frames"] == len(frames)
    np.testing.assert_allclose(provenance["up"], up, atol=1e-6)
    assert cache.rgbd_entry(capture, TINY, frames, up)[0] == path
    assert cache.rgbd_entry(capture, TINY, frames, [0.0, 0.0, 1.0])[0] != path
    # Every training frame: nothing recorded about a selection.
    every = load_field(cache.rgbd_field(capture, TINY)).info.provenance
    assert "train_indices" not in every and "up" not in every and every["train_frames"] == len(capture.train_indices())


def test_a_change_to_noisy_depth_training_renews_only_the_noisy_fields(ours: Capture, tmp_path: Path) -> None:
    """Raising the noisy-depth version gives a sensor capture's field another cache file and
    leaves an exact-depth capture's where it was."""
    from regnf.synthetic import cache as cache_module

    noisy = write_sphere_capture(tmp_path / "noisy", meta={"zero_depth": "unknown"})
    assert noisy.depth_noise is not None and ours.depth_noise is None
    cache = Cache(tmp_path / "cache", progress=False)
    before = cache.rgbd_entry(noisy, TINY)[0], cache.rgbd_entry(ours, TINY)[0]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cache_module, "NOISY_DEPTH_VERSION", cache_module.NOISY_DEPTH_VERSION + 1)
        after = cache.rgbd_entry(noisy, TINY)[0], cache.rgbd_entry(ours, TINY)[0]
    assert after[0] != before[0] and after[1] == before[1]
