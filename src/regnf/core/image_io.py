"""PNG output of renders, written atomically.

Formats:

- RGB: 8-bit, 3 channels (floats in [0, 1] are rounded; uint8 is written as is).
- Depth: 16-bit grey, MILLIMETRES, rounded; 0 means no hit (so the range is 1 mm to
  65.535 m; a hit closer than 0.5 mm is stored as 1 mm, so it is not read back as a miss).
- Instance id: 16-bit grey, ``i`` where instance ``i`` (1..n) is seen, 0 elsewhere (no hit
  and the scene's own surfaces), as COCO and BOP tools expect.

Every file is first written to a temporary file in the destination folder, flushed to
disk and then renamed over the destination with ``os.replace`` (atomic on POSIX and
Windows). On any error the temporary file is removed and an existing destination is left
untouched: a reader never sees a partial PNG.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch
from PIL import Image

from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError

UINT16_MAX = 65535
"""Largest value of a 16-bit PNG sample."""
MAX_DEPTH_MM = UINT16_MAX
"""Largest storable depth in millimetres."""


def _numpy(a: torch.Tensor | np.ndarray) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


PNG_COMPRESS_LEVEL = 1
"""zlib level of the PNGs written, 0-9 (OpenCV's default too): faster to encode than Pillow's
default 6 for files a fifth larger (docs/decisions/rendering-speed.md)."""


def _encode(image: Image.Image, f: BinaryIO) -> None:
    """Encode ``image`` as PNG into the open file ``f`` (a seam for tests)."""
    image.save(f, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


def _atomic_save(path: str | os.PathLike, image: Image.Image) -> Path:
    path = Path(path)
    if not path.parent.is_dir():
        raise RegnfError(f"cannot write {path}: folder {path.parent} does not exist")
    with atomic_path(path, suffix=".tmp") as tmp, open(tmp, "wb") as f:
        _encode(image, f)
        f.flush()
        os.fsync(f.fileno())
    return path


def rgb_to_uint8(rgb: torch.Tensor | np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 of ``rgb`` (h, w, 3): floats in [0, 1] clipped and rounded, uint8 as is."""
    a = _numpy(rgb)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise RegnfError(f"rgb must be (h, w, 3), got {a.shape}")
    if a.dtype == np.uint8:
        return a
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise RegnfError("rgb has non-finite values")
    return np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_rgb_png(path: str | os.PathLike, rgb: torch.Tensor | np.ndarray) -> Path:
    """Write ``rgb`` (h, w, 3), floats in [0, 1] or uint8, as an 8-bit PNG; returns the path."""
    a = rgb_to_uint8(rgb)
    return _atomic_save(path, Image.fromarray(np.ascontiguousarray(a)))


def depth_to_mm(
    depth: torch.Tensor | np.ndarray, mask: torch.Tensor | np.ndarray | None = None
) -> np.ndarray:
    """(h, w) uint16 millimetres of ``depth`` (h, w) metres; 0 where no hit.

    No hit: ``mask`` False (when given), or a depth that is 0 or not finite. Raises
    ``ValueError`` for negative depths or hits beyond 65.535 m.
    """
    dm = _numpy(depth).astype(np.float64)
    if dm.ndim != 2:
        raise RegnfError(f"depth must be (h, w), got {dm.shape}")
    hit = np.isfinite(dm) & (dm != 0)
    if mask is not None:
        mk = _numpy(mask).astype(bool)
        if mk.shape != dm.shape:
            raise RegnfError(f"mask {mk.shape} and depth {dm.shape} differ in shape")
        hit &= mk
    if (dm[hit] < 0).any():
        raise RegnfError(f"depth must be >= 0, got a minimum of {dm[hit].min():.6g} m")
    mm = np.round(np.where(hit, dm, 0.0) * 1000.0)
    if (mm > MAX_DEPTH_MM).any():
        raise RegnfError(
            f"depth {mm.max() / 1000.0:.3f} m exceeds the 16-bit millimetre range "
            f"({MAX_DEPTH_MM / 1000.0} m)"
        )
    return np.where(hit, np.maximum(mm, 1.0), 0.0).astype(np.uint16)


def write_depth_png(
    path: str | os.PathLike,
    depth: torch.Tensor | np.ndarray,
    mask: torch.Tensor | np.ndarray | None = None,
) -> Path:
    """Write ``depth`` (h, w) metres as a 16-bit millimetre PNG, 0 = no hit (see the module)."""
    return _atomic_save(path, Image.fromarray(depth_to_mm(depth, mask)))


def write_instance_png(path: str | os.PathLike, instance_id: torch.Tensor | np.ndarray) -> Path:
    """Write a renderer's ``instance_id`` (h, w) ints in [-1, 65535] as a 16-bit instance PNG.

    The PNG holds the instance id (1..n) where an instance is seen and 0 elsewhere: the
    renderer's -1 (no hit) and 0 (the scene's own surface) both become 0, the background of
    every instance image regnf writes (COCO, BOP and nerfstudio tools read it so).
    """
    ids = _numpy(instance_id)
    if ids.ndim != 2 or not np.issubdtype(ids.dtype, np.integer):
        raise RegnfError(
            f"instance_id must be an (h, w) integer image, got {ids.shape} {ids.dtype}"
        )
    if ids.size and (ids.min() < -1 or ids.max() > UINT16_MAX):
        raise RegnfError(f"instance ids must lie in [-1, {UINT16_MAX}], got [{ids.min()}, {ids.max()}]")
    return _atomic_save(path, Image.fromarray(np.maximum(ids.astype(np.int64), 0).astype(np.uint16)))


def _read_gray16(path: str | os.PathLike) -> np.ndarray:
    with Image.open(path) as im:
        a = np.asarray(im)
    if a.ndim != 2:
        raise RegnfError(f"{path} is not a single-channel image (shape {a.shape})")
    return a.astype(np.int64)


def read_rgb_png(path: str | os.PathLike) -> np.ndarray:
    """(h, w, 3) uint8."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).copy()


def read_depth_png(path: str | os.PathLike) -> np.ndarray:
    """(h, w) float64 metres; 0 where no hit."""
    return _read_gray16(path).astype(np.float64) / 1000.0


def read_instance_png(path: str | os.PathLike) -> np.ndarray:
    """(h, w) int64 instance ids: 1..n an instance, 0 background (see :func:`write_instance_png`)."""
    return _read_gray16(path)
