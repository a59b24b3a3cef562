"""The memory estimate of training: the samples' bytes against the tensors actually built."""

from __future__ import annotations

from pathlib import Path

import pytest

from regnf.captures.formats import read_capture
from regnf.core import preflight
from regnf.observations.rgbd_samples import RGBDSamples, build_samples
from regnf.observations.sample_memory import (
    check_training_memory,
    row_bytes,
    sample_bytes,
    training_bytes,
)
from tests.captures.ns_helpers import H, W, write_nerfstudio


def test_every_field_of_the_samples_is_counted() -> None:
    rows = row_bytes()
    # points, colours, normals, origins: 3 float32 each; the rest at least a byte a row.
    assert rows["surface"] >= 4 * 12 + 3 and rows["free"] >= 2 * 12 and rows["edge"] >= 2 * 12 + 2 * 4
    assert set(rows) == {"surface", "free", "edge"}
    assert len(RGBDSamples._fields) >= 13


@pytest.mark.parametrize("pixel_stride", [1, 2])
def test_the_estimate_matches_the_samples_built(tmp_path: Path, pixel_stride: int) -> None:
    # A room scan: every pixel has depth (zero depth unknown), as a sensor's capture.
    write_nerfstudio(tmp_path / "ns")
    capture, _ = read_capture(tmp_path / "ns")
    indices = capture.train_indices()
    samples = build_samples(capture, indices, pixel_stride)
    actual = sum(t.numel() * t.element_size() for t in samples if t is not None)
    estimate = sample_bytes(len(indices), H, W, pixel_stride)
    assert 0.8 * actual <= estimate <= 1.25 * actual, (estimate, actual)
    assert training_bytes(len(indices), H, W, pixel_stride) > estimate


def test_training_larger_than_the_free_memory_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(preflight, "available_memory_bytes", lambda: 10**9)
    check_training_memory("cap", 10, 48, 64, 1)  # a few MB: fine
    with pytest.raises(preflight.PreflightError) as refused:
        check_training_memory("cap", 600, 480, 640, 1)
    need = training_bytes(600, 480, 640, 1) / 1e9
    assert str(refused.value) == (f"cap: training 600 frames of 640x480 at pixel stride 1 needs about {need:.1f} GB, "
                                  "1.0 GB is free; use --training.pixel-stride or --max-frames")
