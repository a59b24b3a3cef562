"""One writer at a time per stage folder, and a cheap check that a stage can be written.

Every change to a stage is a read-modify-write (read the stage, add to it, write every file).
Two processes doing it at once would both read the old stage and the second write would
drop the first one's change, so every writer in :mod:`scene_graph` holds :func:`stage_lock`
(the POSIX lock of :mod:`regnf.core.file_lock` on ``.regnf.lock`` in the stage's folder) from
before the read until after the write. Readers take no lock: files are replaced atomically
and the root layer last, and a reader may have no right to write the folder at all.

The lock nests within a thread (an edit holding it calls :func:`write_stage`, which takes it
too; a command holding its output folder writes a stage there), and a waiting writer gives
up after :data:`STAGE_LOCK_TIMEOUT_S`.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from regnf.core.file_lock import LOCK_NAME, folder_lock

from . import layout as L
from .errors import StageError
from .usd_read import check_stage_file, read_stage

STAGE_LOCK_TIMEOUT_S = 60.0
"""Seconds a writer waits for another writer of the same stage folder before it raises
``regnf.core.file_lock.LockBusy``. An edit holds the lock well under a second (an export of a
large stage a few seconds), so a full minute only runs out when something is stuck."""

def _make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and missing parents; return those created, outermost first."""
    missing = []
    p = folder
    while not p.exists():
        missing.append(p)
        p = p.parent
    made = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except FileExistsError:  # another writer made it meanwhile
            continue
        made.append(d)
    return made


@contextlib.contextmanager
def stage_lock(stage_path: str | os.PathLike, create: bool = False) -> Iterator[Path]:
    """Hold the lock of the folder of ``stage_path`` (a stage, a layer or a package to write).

    Parameters
    ----------
    stage_path : str or PathLike
        The stage to change, or with ``create`` the file about to be made; its folder is
        locked.
    create : bool
        ``False``: ``stage_path`` must exist (an edit), so that a mistyped path leaves no lock
        file behind. ``True``: the file may be new, and its folder is created if missing (a
        new stage, an export); folders made here are removed again if the block fails and
        leaves them empty (but for the lock file).

    Yields
    ------
    Path
        The locked folder.

    Raises
    ------
    StageError
        The stage is missing (and not ``create``), or the lock file cannot be created or
        opened (a folder the user cannot write).
    regnf.core.file_lock.LockBusy
        Another process still holds the lock after :data:`STAGE_LOCK_TIMEOUT_S` seconds.
    regnf.core.file_lock.LockUnavailable
        The file system cannot lock (some SMB and FUSE mounts).
    """
    stage_path = Path(stage_path).absolute()
    folder = stage_path.parent
    if not create:
        check_stage_file(stage_path)
    made = _make_folders(folder) if create else []
    try:
        with contextlib.ExitStack() as stack:
            try:
                stack.enter_context(folder_lock(folder, f"the stage folder {folder}", STAGE_LOCK_TIMEOUT_S))
            except (PermissionError, FileNotFoundError, NotADirectoryError) as exc:
                raise StageError(folder / LOCK_NAME, "/", f"cannot take the lock of the stage's folder to write "
                                 f"{stage_path.name}: {exc.strerror or exc}") from exc
            yield folder
    except BaseException:
        if made:
            (folder / LOCK_NAME).unlink(missing_ok=True)
            for d in reversed(made):
                with contextlib.suppress(OSError):  # not empty: something else lives there now
                    d.rmdir()
        raise


def check_writable(stage_path: str | os.PathLike, allow_outside: bool = False) -> Path:
    """Check, before a long computation, that an edit of the stage could be written.

    Cheap: the stage is read without parsing its checkpoints, and the folder is probed with
    ``os.access`` (nothing is written).

    Parameters
    ----------
    stage_path : str or PathLike
        A regnf stage (.usda or .usdc) to add to.
    allow_outside : bool
        As for :func:`regnf.scene_graph.read_stage`.

    Returns
    -------
    Path
        The stage's absolute path.

    Raises
    ------
    StageError
        Naming the file and the problem: no such stage, not a regnf stage (or one
        :func:`read_stage` refuses), a package or another suffix than .usda / .usdc, a folder,
        asset folder, root layer or lock file the user cannot write.
    """
    path = Path(stage_path).absolute()
    check_stage_file(path)
    if path.suffix not in L.STAGE_SUFFIXES:
        raise StageError(path, "/", f"only a {' or '.join(L.STAGE_SUFFIXES)} stage can be edited "
                         "(export a package to .usda first)")
    read_stage(path, check_checkpoints=False, allow_outside=allow_outside)
    folder = path.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise StageError(folder, "/", f"the stage's folder is not writable, so {path.name} cannot be changed "
                         "(files are replaced by renaming temporaries in it)")
    if not os.access(path, os.W_OK):
        raise StageError(path, "/", "the stage's root layer is not writable")
    for sub in (L.FIELDS_DIR, L.LIBRARY_DIR, L.SLOTS_DIR):
        d = folder / sub
        if d.is_dir() and not os.access(d, os.W_OK | os.X_OK):
            raise StageError(d, "/", f"the stage's {sub}/ folder is not writable")
    lock = folder / LOCK_NAME
    if lock.exists() and not os.access(lock, os.R_OK | os.W_OK):
        raise StageError(lock, "/", "the stage's lock file cannot be opened for writing (made by another user?)")
    return path
