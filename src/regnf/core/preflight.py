"""Checks a command makes before it starts work: what it reads, where it writes, and whether it
fits in memory and on the disk.

A command that would fail after minutes of training or rendering (an output path that is a
folder, a folder it cannot write, an image that cannot fit in memory, a data set larger than
the free disk) fails here at once with one line that names the path or the option and the
problem; so does one whose input would never finish reading (a FIFO, ``/dev/zero``, a JSON
file of gigabytes), which is refused without being opened. Every check raises
:class:`PreflightError` (a ``ValueError``); the command line turns it into that line and
exit status 1 (see :mod:`regnf.cli.app`).
"""

from __future__ import annotations

import json
import os
import shutil
import stat
from pathlib import Path
from typing import Any, BinaryIO

from regnf.core.errors import RegnfError

MEMORY_FRACTION = 0.8
"""A job may plan to use at most this fraction of the memory available when it starts."""
RENDER_BYTES_PER_PIXEL = 64
"""Memory a rendered pixel holds until its view is written: ray origin and direction, RGB,
depth, normal, mask, instance id and the tracer's per-ray state (float32 / int64)."""
MESH_BYTES_PER_NODE = 24
"""Memory per node of the marching-cubes grid: the float32 SDF volume plus what
``skimage.measure.marching_cubes`` allocates beside it (docs/decisions/training_memory.md)."""
MAX_JSON_BYTES = 16 * 2**20
"""Largest JSON input file (a box, a registration result, a record in an output folder), in bytes."""


class PreflightError(RegnfError):
    """A command cannot start: the message names the path or option and the problem."""


class JsonInputError(PreflightError):
    """A JSON input that cannot be read (:func:`read_json_input`): ``"<where>: <problem>"``.

    Parameters
    ----------
    where : str
        The option and the file (``--box box.json``), or the file alone.
    problem : str
        What is wrong, in words, for a caller that words the message its own way.
    """

    def __init__(self, where: str, problem: str) -> None:
        self.where = where
        self.problem = problem
        super().__init__(f"{where}: {problem}")


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


_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def input_file_problem(path: str | os.PathLike, missing: str = "no such file") -> str | None:
    """Why ``path`` cannot be read as a regular file, or None when it can.

    Found with ``os.stat`` alone: a folder, a FIFO or a device is refused without being opened
    (opening a FIFO waits for a writer; ``/dev/zero`` never ends).

    Parameters
    ----------
    path : str or PathLike
    missing : str
        The problem to give when nothing is there.

    Returns
    -------
    str or None
        ``missing``, ``"is not a file (a folder)"`` (or a FIFO, a device...), ``"is not readable"``.
    """
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return missing
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
        return f"is not a file ({kind})"
    if not os.access(path, os.R_OK):
        return "is not readable"
    return None


def check_input_file(path: str | os.PathLike, option: str, what: str = "file") -> Path:
    """``path`` is an existing, readable regular file (:func:`input_file_problem`)."""
    path = Path(path)
    problem = input_file_problem(path, f"no such {what}")
    if problem is not None:
        raise PreflightError(f"{option} {path}: {problem}")
    return path


def open_regular_file(path: str | os.PathLike) -> tuple[BinaryIO, int] | None:
    """``path`` opened for reading, and its size in bytes; None when it is not a regular file.

    The open does not block and the check is made on the open file, so a FIFO or device put in
    the place of a file checked before cannot block the read.

    Raises
    ------
    OSError
        It cannot be opened.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    f = os.fdopen(fd, "rb")
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        f.close()
        return None
    return f, st.st_size


def read_json_input(path: str | os.PathLike, option: str | None, what: str = "JSON file",
                    max_bytes: int = MAX_JSON_BYTES) -> Any:
    """The JSON value of a file the user named, read only if it is a regular file of at most ``max_bytes``.

    Parameters
    ----------
    path : str or PathLike
    option : str or None
        The option that named it (``--box``), for the message; None for a file found in a folder.
    what : str
        What the file holds, for the message (``"box"``, ``"registration result"``).
    max_bytes : int
        Largest size read, in bytes.

    Raises
    ------
    JsonInputError
        (a :class:`PreflightError`) One line naming the option and the file: missing, not a
        regular file (a folder, FIFO or device: refused without being opened), unreadable,
        larger than ``max_bytes``, or not UTF-8 JSON.
    """
    path = Path(path)
    where = f"{option} {path}" if option else str(path)
    problem = input_file_problem(path, f"no such {what}")
    if problem is not None:
        raise JsonInputError(where, problem)
    try:
        opened = open_regular_file(path)
        if opened is None:
            raise JsonInputError(where, "is not a file")
        f, size = opened
        with f:
            if size > max_bytes:
                raise JsonInputError(where, f"{size:,} bytes, more than the {max_bytes:,} a {what} "
                                     "may have (is it the right file?)")
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise JsonInputError(where, f"cannot read the {what} ({exc.strerror or exc})") from exc
    if len(data) > max_bytes:
        raise JsonInputError(where, f"more than the {max_bytes:,} bytes a {what} may have (is it the right file?)")
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise JsonInputError(where, f"cannot read the {what} (not UTF-8 JSON: {exc})") from exc


def free_bytes(path: str | os.PathLike) -> int:
    """Bytes free to this user on the file system that holds ``path`` (or would: its nearest existing folder)."""
    return shutil.disk_usage(_nearest_existing(Path(path).absolute())).free


def check_free_space(folder: str | os.PathLike, needed_bytes: float, what: str) -> None:
    """Refuse a job that would write more than the file system holding ``folder`` has free.

    Raises
    ------
    PreflightError
        ``"<what> needs about X GB in FOLDER, Y GB free"``.
    """
    free = free_bytes(folder)
    if needed_bytes > free:
        scale, unit = (1e9, "GB") if needed_bytes >= 1e9 else (1e6, "MB")  # one unit for both figures
        raise PreflightError(f"{what} needs about {needed_bytes / scale:.2f} {unit} in {folder}, "
                             f"{free / scale:.2f} {unit} free; free some space or write elsewhere")


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
