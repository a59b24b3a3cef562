"""How much memory training on a capture needs, checked before any depth is read.

Training holds every sample of its frames (:class:`~regnf.observations.rgbd_samples.RGBDSamples`)
and the depth images of its views (the projective free-space test), and building the samples
holds more at its peak than the samples themselves. The bytes a sample row takes are read off
the fields of ``RGBDSamples`` (:func:`row_bytes`), so the estimate follows them when they change;
the factors on top are measured (docs/decisions/training_memory.md).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from regnf.captures.model import Capture, CaptureFrame
from regnf.core import preflight
from regnf.observations.rgbd_samples import build_samples

EDGE_SHARE = 0.1
"""Rows of occluding-edge rays per pixel assumed (a room scan at 640 x 480 has a few per cent)."""

BUILD_PEAK = 2.0
"""Peak memory while the samples are built, as a multiple of the samples' own bytes (each
frame's float32 parts and the joined tensors; docs/decisions/training_memory.md)."""

VIEW_STACK_PEAK = 2.0
"""Peak memory of the views' depth stack, as a multiple of its float32 bytes (it is stacked, then copied)."""

FIXED_BYTES = 512 * 2**20
"""Bytes for everything that does not grow with the frames: the field, its optimiser, a step's
batch, the visibility grid."""


class _Probe(Capture):
    """A 6 x 6 one-frame capture held in memory: the smallest input :func:`build_samples` takes.

    Its zeros are empty (free rays) and its depth has a noise model (per-sample weights and
    sigmas), so that every field of ``RGBDSamples`` is filled."""

    def rgb(self, i: int) -> np.ndarray:
        return np.zeros((self.height, self.width, 3), dtype=np.float32)

    def depth(self, i: int) -> np.ndarray | None:
        depth = np.ones((self.height, self.width), dtype=np.float32)
        depth[:, :2] = 0.5  # a step: an occluding edge
        depth[0, -1] = 0.0  # a pixel without depth: a free ray
        return depth


@functools.lru_cache(maxsize=1)
def row_bytes() -> dict[str, int]:
    """Bytes of one row of each kind of sample: ``surface``, ``free`` and ``edge`` rays.

    Every field of ``RGBDSamples`` counts towards the kind its name starts with (``free_``,
    ``edge_``, else a surface sample); its row's bytes are its trailing shape times its element
    size, as built from a tiny in-memory capture.
    """
    K = np.array([[6.0, 0.0, 3.0], [0.0, 6.0, 3.0], [0.0, 0.0, 1.0]])
    frame = CaptureFrame(Path("probe.png"), Path("probe.npy"), np.eye(4), K)
    probe = _Probe(Path("probe"), 6, 6, [frame], np.eye(4), {}, meta={"zero_depth": "empty"})
    samples = build_samples(probe, [0])
    out = {"surface": 0, "free": 0, "edge": 0}
    for name, tensor in samples._asdict().items():
        if tensor is None:  # an optional field this capture does not fill
            continue
        kind = next((k for k in ("free", "edge") if name.startswith(f"{k}_")), "surface")
        out[kind] += math.prod(tensor.shape[1:]) * tensor.element_size()
    return out


def sample_pixels(height: int, width: int, pixel_stride: int) -> int:
    """Pixels of one frame that give samples at ``pixel_stride`` (every stride-th row and column)."""
    return math.ceil(height / pixel_stride) * math.ceil(width / pixel_stride)


def sample_bytes(n_frames: int, height: int, width: int, pixel_stride: int = 1) -> int:
    """Bytes of the samples of ``n_frames`` frames of ``width x height``: each pixel a surface
    sample or a free ray (the larger), and :data:`EDGE_SHARE` of an edge ray."""
    rows = row_bytes()
    per_pixel = max(rows["surface"], rows["free"]) + EDGE_SHARE * rows["edge"]
    return int(n_frames * sample_pixels(height, width, pixel_stride) * per_pixel)


def training_bytes(n_frames: int, height: int, width: int, pixel_stride: int = 1) -> int:
    """Memory training needs at its peak: the samples while they are built, the views' depth stack
    (full resolution, float32) and :data:`FIXED_BYTES`.

    Parameters
    ----------
    n_frames : int
        Training frames.
    height, width : int
        Depth image size, pixels.
    pixel_stride : int
        Samples from every ``pixel_stride``-th row and column.

    Returns
    -------
    int
        Bytes.
    """
    views = VIEW_STACK_PEAK * n_frames * height * width * np.dtype(np.float32).itemsize
    return int(BUILD_PEAK * sample_bytes(n_frames, height, width, pixel_stride) + views + FIXED_BYTES)


def check_training_memory(where: str, n_frames: int, height: int, width: int, pixel_stride: int = 1) -> None:
    """Refuse training that needs more memory than is available (before any depth is read).

    Parameters
    ----------
    where : str
        The capture, for the message.
    n_frames, height, width, pixel_stride
        As for :func:`training_bytes`.

    Raises
    ------
    regnf.core.preflight.PreflightError
        ``"<where>: training N frames of WxH at pixel stride S needs about X GB, Y GB is free;
        use --training.pixel-stride or --max-frames"``.
    """
    needed = training_bytes(n_frames, height, width, pixel_stride)
    free = preflight.available_memory_bytes()
    if needed > free:
        raise preflight.PreflightError(
            f"{where}: training {n_frames} frames of {width}x{height} at pixel stride {pixel_stride} needs "
            f"about {needed / 1e9:.1f} GB, {free / 1e9:.1f} GB is free; use --training.pixel-stride or --max-frames"
        )
