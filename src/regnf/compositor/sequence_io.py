"""Image sequences (the RGB views of a render, in order) as an animated GIF or an MP4 video.

Both writers are atomic like :mod:`regnf.core.image_io`: the file is written to a
temporary file in the destination folder, flushed and renamed over the destination; on
any error the temporary file is removed and an existing destination is left untouched.

- GIF: Pillow, looping forever, one adaptive 256-colour palette per frame. Frame times are
  stored in centiseconds (``fps`` 10 is exact; viewers slow down frames under 20 ms).
  Pillow merges a frame identical to the one before it into a single longer frame, so a
  sequence with repeated frames reads back with fewer frames (the timing is kept).
- MP4: H.264 (``libx264``, ``yuv420p``) through ``imageio`` with the ``imageio-ffmpeg``
  package, which is optional: without it :func:`write_mp4` raises
  :class:`SequenceBackendError`. ``yuv420p`` needs even sizes: an odd last row or column
  is repeated.
"""

from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import BinaryIO, Literal

import numpy as np
import torch
from PIL import Image

from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError
from regnf.core.image_io import rgb_to_uint8

SEQUENCE_FORMATS = ("none", "gif", "mp4")
"""Values of the ``sequence`` settings: no sequence, an animated GIF, an MP4 video."""
MP4_PACKAGE = "imageio-ffmpeg"
"""The package :func:`write_mp4` needs (it brings its own ffmpeg)."""

Frames = Sequence[np.ndarray | torch.Tensor]
"""(h, w, 3) RGB images, uint8 or floats in [0, 1], all of one size."""


class SequenceBackendError(ImportError):
    """The package needed to write a video format is not installed."""


def _frames(frames: Frames) -> list[np.ndarray]:
    """The frames as (h, w, 3) uint8; ``ValueError`` for none, a bad one, or differing sizes."""
    if len(frames) == 0:
        raise RegnfError("a sequence needs at least one frame")
    out = []
    for k, frame in enumerate(frames):  # a loop over frames, each converted whole
        try:
            a = np.ascontiguousarray(rgb_to_uint8(frame))
        except ValueError as exc:
            raise RegnfError(f"frame {k}: {exc}") from exc
        if out and a.shape != out[0].shape:
            raise RegnfError(f"frame {k} is {a.shape[1]} x {a.shape[0]} pixels, frame 0 is "
                             f"{out[0].shape[1]} x {out[0].shape[0]}: a sequence needs one size")
        out.append(a)
    return out


def _check(path: Path, fps: float) -> None:
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise RegnfError(f"fps must be finite and > 0, got {fps}")
    if not path.parent.is_dir():
        raise RegnfError(f"cannot write {path}: folder {path.parent} does not exist")


def _encode_gif(frames: list[np.ndarray], f: BinaryIO, fps: float) -> None:
    """Encode ``frames`` as a looping GIF into the open file ``f`` (a seam for tests)."""
    images = [Image.fromarray(a) for a in frames]
    images[0].save(f, format="GIF", save_all=True, append_images=images[1:],
                   duration=round(1000.0 / fps), loop=0)


def write_gif(path: str | os.PathLike, frames: Frames, fps: float = 10) -> Path:
    """Write ``frames`` as an animated GIF looping forever, atomically (see the module).

    Parameters
    ----------
    path : str or PathLike
        Destination; its folder must exist. Replaced if present.
    frames : sequence of (h, w, 3) uint8 arrays (or floats in [0, 1])
        At least one, all of one size, in order.
    fps : float
        Frames per second (> 0).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        No frame, frames of different sizes or not RGB, a bad ``fps``, a missing folder;
        nothing is written then.
    """
    path = Path(path)
    _check(path, fps)
    images = _frames(frames)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        _encode_gif(images, f, fps)
        f.flush()
        os.fsync(f.fileno())
    return path


def mp4_available() -> bool:
    """Whether :func:`write_mp4` can write (``imageio-ffmpeg`` is installed)."""
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def require_mp4() -> None:
    """Raise :class:`SequenceBackendError` naming the missing package unless MP4 can be written."""
    if not mp4_available():
        raise SequenceBackendError(
            f"writing MP4 needs the package {MP4_PACKAGE} (an ffmpeg backend for imageio), which is "
            f"not installed: `pip install {MP4_PACKAGE}`, or write a GIF instead"
        )


def _even(a: np.ndarray) -> np.ndarray:
    """``a`` (h, w, 3) with its last row / column repeated to make both sizes even."""
    h, w = a.shape[:2]
    return np.pad(a, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _encode_mp4(frames: list[np.ndarray], tmp: Path, fps: float) -> None:
    """Encode ``frames`` as H.264 into the file ``tmp`` (a seam for tests)."""
    import imageio.v2 as imageio

    with imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                            pixelformat="yuv420p", macro_block_size=1) as writer:
        for a in frames:  # a loop over frames
            writer.append_data(_even(a))


def write_mp4(path: str | os.PathLike, frames: Frames, fps: float = 10) -> Path:
    """Write ``frames`` as an H.264 MP4 video, atomically (see the module).

    Parameters
    ----------
    path : str or PathLike
        Destination; its folder must exist. Replaced if present.
    frames : sequence of (h, w, 3) uint8 arrays (or floats in [0, 1])
        At least one, all of one size, in order.
    fps : float
        Frames per second (> 0).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    SequenceBackendError
        ``imageio-ffmpeg`` is not installed (an ``ImportError``).
    ValueError
        As :func:`write_gif`. Nothing is written on any error.
    """
    path = Path(path)
    _check(path, fps)
    images = _frames(frames)
    require_mp4()
    with atomic_path(path) as tmp:
        _encode_mp4(images, tmp, fps)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
    return path


def write_sequence(
    path: str | os.PathLike, frames: Frames, kind: Literal["gif", "mp4"], fps: float = 10
) -> Path:
    """:func:`write_gif` or :func:`write_mp4` by ``kind``."""
    if kind == "gif":
        return write_gif(path, frames, fps)
    if kind == "mp4":
        return write_mp4(path, frames, fps)
    raise RegnfError(f"sequence kind must be 'gif' or 'mp4', got {kind!r}")
