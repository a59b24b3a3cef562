"""Atomic file writes: a reader sees the old file or the new one, never half of one.

Everything regnf writes (images, JSON, checkpoints, meshes, stages) goes through these
helpers: write to a temporary file in the destination folder, flush, then ``os.replace``.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

TEMP_PREFIX = ".regnf-tmp-"
"""Prefix of every temporary file or folder regnf makes beside a destination. A leftover one
(from a killed run) is ours to remove; nothing without it is."""


def user_mode(path: str | os.PathLike, directory: bool = False) -> None:
    """Give ``path`` the permissions a plain ``open`` or ``mkdir`` would under the user's umask.

    ``tempfile.mkstemp`` and ``mkdtemp`` make private (0600 / 0700) entries; a stage or data
    set shared with a cluster must be readable as the user's umask says.
    """
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if directory else 0o666) & ~umask)


def temp_beside(dest: str | os.PathLike, suffix: str | None = None) -> Path:
    """A new, empty temporary file (:data:`TEMP_PREFIX`, the user's permissions) in ``dest``'s
    folder, to be renamed over ``dest``; ``suffix`` defaults to the destination's suffix, so
    that libraries that pick a format from the file name (imageio, trimesh) still do."""
    dest = Path(dest)
    fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{dest.name}.",
                               suffix=dest.suffix if suffix is None else suffix, dir=dest.parent)
    os.close(fd)
    user_mode(tmp)
    return Path(tmp)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; it replaces ``path`` only if the block succeeds.

    ``suffix`` defaults to the destination's suffix, so that libraries that pick a format
    from the file name (imageio, trimesh) still do.
    """
    dest = Path(path)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp_path = temp_beside(dest, suffix)
    except OSError as exc:
        named = naming(exc, dest)
        if named is exc:
            raise
        raise named from exc
    try:
        yield tmp_path
        os.replace(tmp_path, dest)
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        named = naming(exc, dest) if isinstance(exc, OSError) else exc
        if named is exc:
            raise
        raise named from exc


def naming(exc: OSError, dest: Path) -> OSError:
    """``exc`` naming ``dest`` when it names no file or our temporary one (a full disk, a refused
    write, a failed rename), so that the one-line message says which file could not be written;
    ``exc`` itself when it names only other files (a folder that could not be made)."""
    names = [Path(str(n)).name for n in (exc.filename, exc.filename2) if n is not None]
    if exc.errno is None or (names and not any(n.startswith(TEMP_PREFIX) for n in names)):
        return exc
    return type(exc)(exc.errno, exc.strerror or os.strerror(exc.errno), str(dest))


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Atomically write ``data`` to ``path``."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_text(path: str | os.PathLike, text: str) -> None:
    """Atomically write UTF-8 ``text`` to ``path``."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> None:
    """Atomically write ``obj`` as JSON (keys kept in insertion order)."""
    write_text(path, json.dumps(obj, indent=indent) + "\n")
