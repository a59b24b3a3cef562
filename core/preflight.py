"""Checks a command makes before it starts work: where it writes, and whether it fits in memory.

A command that would fail after minutes of training or rendering (an output path that is a
folder, a folder it cannot write, an image that cannot fit in memory) fails here at once
with one line that names the path or the option and the problem. Every check raises
:class:`PreflightError` (a ``ValueError``); the command line turns it into that line and
exit status 1 (see :mod:`regnf.cli`).
"""

from __future__ import annotations

import os
from pathlib import Path

MEMORY_FRACTION = 0.8
"""A job may plan to use at most this fraction of the memory available when it starts."""
RENDER_BYTES_PER_PIXEL = 64
"""Memory a rendered pixel holds until its view is written: ray origin and direction, RGB,
depth, normal, mask, instance id and the tracer's per-ray state (float32 / int64)."""
MESH_BYTES_PER_NODE = 24
"""Memory per node of the marching-cubes grid: the float32 SDF volume plus what
``skimage.measure.marching_cubes`` allocates beside it (measured at about 5x the volume)."""


class PreflightError(ValueError):
    """A command cannot start: the message names the path or option and the problem."""


def available_memory_bytes() -> int:
    """Memory this process can still use: ``MemAvailable`` of ``/proc/meminfo``, else physical memory."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(needed_bytes: float, what: str) -> None:
    """Refuse a job that plans to use more than :data:`MEMORY_FRACTION` of the available memory."""
    budget = MEMORY_FRACTION * available_memory_bytes()
    if needed_bytes > budget:
        raise PreflightError(f"{what} needs about {needed_bytes / 2**30:.1f} GiB of memory, more than the "
                             f"{budget / 2**30:.1f} GiB available; make it smaller")


def check_image_size(width: int, height: int, max_pixels: int, option: str = "--width/--height") -> None:
    """Refuse, before anything is loaded, an image of more than ``max_pixels`` pixels (the
    renderer's limit, :data:`regnf.compositor.render_folder.MAX_PIXELS`) or one that cannot fit
    in memory."""
    if width < 1 or height < 1:
        raise PreflightError(f"{option}: the image size must be at least 1 x 1, got {width} x {height}")
    if width * height > max_pixels:
        raise PreflightError(f"{option}: a view of {width} x {height} pixels is more than the "
                             f"{max_pixels:,} pixels a view may have; render smaller views")
    check_memory(width * height * RENDER_BYTES_PER_PIXEL, f"{option}: a {width} x {height} image")


def check_mesh_resolution(resolution: int, option: str = "--resolution") -> None:
    """Refuse a marching-cubes grid that cannot fit in memory (before any field is loaded)."""
    if resolution < 2:
        raise PreflightError(f"{option} must be at least 2, got {resolution}")
    # The longest axis gets ``resolution`` cells; the others at most as many.
    check_memory(float(resolution + 1) ** 3 * MESH_BYTES_PER_NODE, f"{option} {resolution}")


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _check_creatable(path: Path, option: str) -> None:
    """``path`` does not exist yet: the nearest existing folder above it must be a writable folder."""
    parent = _nearest_existing(path.parent)
    if not parent.is_dir():
        raise PreflightError(f"{option} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PreflightError(f"{option} {path}: the folder {parent} is not writable")


def check_output_file(path: str | os.PathLike, option: str = "--out", suffix: str | None = None) -> Path:
    """``path`` can be written as a file: not a folder, in (or below) a writable folder.

    An existing file is fine: writes replace it atomically. ``suffix``, if given, is required.
    """
    path = Path(path)
    if suffix is not None and path.suffix != suffix:
        raise PreflightError(f"{option} {path}: must end in {suffix}")
    if path.is_dir():
        raise PreflightError(f"{option} {path}: is a folder, expected a file name")
    if path.exists():
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise PreflightError(f"{option} {path}: the folder {path.parent} is not writable")
        return path
    _check_creatable(path, option)
    return path


def check_output_dir(path: str | os.PathLike, option: str = "--out") -> Path:
    """``path`` can be written as a folder: an existing writable folder, or creatable."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise PreflightError(f"{option} {path}: is a file, expected a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise PreflightError(f"{option} {path}: the folder is not writable")
        return path
    _check_creatable(path, option)
    return path


def check_input_file(path: str | os.PathLike, option: str, what: str = "file") -> Path:
    """``path`` is an existing, readable file."""
    path = Path(path)
    if not path.exists():
        raise PreflightError(f"{option} {path}: no such {what}")
    if not path.is_file():
        raise PreflightError(f"{option} {path}: is not a file")
    if not os.access(path, os.R_OK):
        raise PreflightError(f"{option} {path}: is not readable")
    return path


def check_device(device: str, option: str = "--device") -> str:
    """Refuse a torch device this machine does not have (``cuda`` without a GPU or a CUDA build).

    Returns
    -------
    str
        ``device`` as given.
    """
    import torch

    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError) as exc:
        raise PreflightError(f"{option} {device}: not a torch device (cpu, cuda or cuda:N)") from exc
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            raise PreflightError(f"{option} {device}: CUDA is not available here (torch {torch.__version__}"
                                 f"{', a CPU build' if torch.version.cuda is None else ', no GPU found'})")
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            raise PreflightError(f"{option} {device}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif parsed.type != "cpu":
        raise PreflightError(f"{option} {device}: only cpu and cuda are supported")
    return device
