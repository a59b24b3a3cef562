"""Reading one frame's depth file: float ``.npy`` or 16-bit PNG, checked, then scaled.

Every capture format stores z-depth in one of these encodings; the reader states, per frame,
the factor from the file's unit to the unit wanted (:attr:`CaptureFrame.depth_scale`). The
messages here name no file: the caller prefixes where.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from regnf.core.errors import RegnfError

PNG_SUFFIXES = (".png",)
"""Depth files read as 16-bit integer images (any other suffix is read as ``.npy``)."""


def _read_npy(path: Path, height: int, width: int) -> np.ndarray:
    """(H, W) float32 from a ``.npy`` of real floating point values."""
    try:
        # Memory-mapped: the dtype and shape are checked before anything is read, so a
        # forged header asking for terabytes costs nothing.
        stored = np.load(path, allow_pickle=False, mmap_mode="r")
    except Exception as exc:  # corrupt, truncated or non-npy file
        hint = "" if path.suffix.lower() == ".npy" else "; depth must be a float .npy or a 16-bit .png"
        raise RegnfError(f"cannot read depth ({exc}){hint}") from exc
    if not isinstance(stored, np.ndarray):
        # A bad file, not a bad argument: the capture's error type, a ValueError.
        raise RegnfError(f"depth must be one .npy array, got {type(stored).__name__}")
    if stored.dtype.kind != "f":
        raise RegnfError(
            f"depth has dtype {stored.dtype}, expected real floating point "
            "(float16, float32 or float64)"
        )
    if np.squeeze(stored).shape != (height, width):
        raise RegnfError(f"depth shape {stored.shape} does not match {height}x{width}")
    # Cast first: a float64 value beyond float32's range becomes inf and is refused later.
    with np.errstate(over="ignore"):
        depth = np.squeeze(np.asarray(stored, dtype=np.float32))
    del stored
    return depth


def _read_png(path: Path, height: int, width: int) -> np.ndarray:
    """(H, W) float32 of the integer values of a single-channel 16-bit PNG."""
    try:
        props = iio.improps(path, extension=".png")
    except Exception as exc:  # imageio raises many types for unreadable files
        raise RegnfError(f"cannot read depth PNG ({exc})") from exc
    if props.dtype != np.uint16:
        bits = 8 * np.dtype(props.dtype).itemsize
        raise RegnfError(
            f"depth PNG is {bits}-bit ({props.dtype}); depth must be a 16-bit PNG "
            "(an 8-bit image cannot hold depth)"
        )
    if tuple(props.shape) != (height, width):
        raise RegnfError(
            f"depth PNG shape {tuple(props.shape)} does not match {height}x{width} single-channel"
        )
    try:
        img = iio.imread(path, extension=".png")
    except Exception as exc:
        raise RegnfError(f"cannot read depth PNG ({exc})") from exc
    return img.astype(np.float32)


def read_depth(
    path: Path, height: int, width: int, scale: float = 1.0, nonfinite_unknown: bool = False
) -> np.ndarray:
    """Z-depth of one frame, (H, W) float32, in the file's unit times ``scale``.

    Parameters
    ----------
    path : Path
        A ``.png`` (uint16, single channel) or a ``.npy`` (real floating point).
    height, width : int
        The capture's image size in pixels.
    scale : float
        Wanted unit per unit stored in the file (1.0: as stored, no arithmetic).
    nonfinite_unknown : bool
        Read NaN and infinite values as 0 (no depth) instead of refusing them: for captures
        whose zeros mean unknown, where a sensor's NaN means no return too.

    Returns
    -------
    (H, W) float32
        Depth, 0 where the file has no depth.

    Raises
    ------
    ValueError
        Unreadable or pickled file, an 8-bit PNG, a dtype that is not real floating point
        (``.npy``), a wrong shape, negative values, or (without ``nonfinite_unknown``) NaN or
        infinite ones. The message names no file.
    """
    path = Path(path)
    reader = _read_png if path.suffix.lower() in PNG_SUFFIXES else _read_npy
    depth = reader(path, height, width)
    if scale != 1.0:
        with np.errstate(over="ignore"):
            depth = depth * np.float32(scale)
    nonfinite = ~np.isfinite(depth)
    bad = int(np.count_nonzero(nonfinite))
    if bad and nonfinite_unknown:
        depth = np.where(nonfinite, np.float32(0.0), depth)
    elif bad:
        raise RegnfError(f"depth has {bad} non-finite values (NaN or inf)")
    negative = int(np.count_nonzero(depth < 0))
    if negative:
        raise RegnfError(
            f"depth has {negative} negative values (min {float(depth.min()):g}); "
            "z-depth must be >= 0, 0 meaning no depth"
        )
    return depth


CONFIDENCE_LEVELS = 3
"""Depth confidence values are 0 (low), 1 (medium) and 2 (high), as ARKit writes them."""


def read_confidence(path: Path, height: int, width: int) -> np.ndarray:
    """Per-pixel depth confidence of one frame, (H, W) uint8 in {0, 1, 2} (ARKit's levels).

    Parameters
    ----------
    path : Path
        A single-channel uint8 image (``.png``...) or a uint8 ``.npy``.
    height, width : int
        The size of the frame's depth, pixels.

    Raises
    ------
    ValueError
        Unreadable or pickled file, a dtype other than uint8, a size other than the depth's,
        or a value above 2. The message names no file.
    """
    path = Path(path)
    try:
        if path.suffix.lower() == ".npy":
            conf = np.load(path, allow_pickle=False, mmap_mode="r")
        else:
            # The extension hint stops imageio from probing every plugin on a corrupt file.
            conf = iio.imread(path, extension=path.suffix or None)
    except Exception as exc:  # numpy and imageio raise many types for unreadable files
        raise RegnfError(f"cannot read depth confidence ({exc})") from exc
    if not isinstance(conf, np.ndarray) or conf.dtype != np.uint8:
        dtype = conf.dtype if isinstance(conf, np.ndarray) else type(conf).__name__
        raise RegnfError(f"depth confidence has dtype {dtype}, expected uint8 (0 low, 1 medium, 2 high)")
    if conf.shape != (height, width):
        raise RegnfError(f"depth confidence shape {conf.shape} does not match the depth's {height}x{width}")
    conf = np.array(conf)
    top = int(conf.max()) if conf.size else 0
    if top >= CONFIDENCE_LEVELS:
        raise RegnfError(f"depth confidence has values up to {top}; expected 0 (low), 1 (medium) or 2 (high)")
    return conf
