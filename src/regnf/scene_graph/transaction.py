"""Multi-file atomic writes: every file of a stage is written to a temporary file first, and
the set replaces the old files only once all of them are written.

If anything fails before the commit, the temporaries (and folders this transaction created)
are removed and the disk is as it was. During the commit each file is replaced with
``os.replace``; the old versions are kept as hard links until the end so that a failure half
way restores them. Callers stage the root layer last, so a reader opening it meanwhile finds
either the old stage or the new one with all its assets.

Temporaries are named ``.regnf-tmp-<name>.*`` (:data:`regnf.core.atomic_io.TEMP_PREFIX`, which
marks what a killed run left as ours to remove) and every file put in place gets the mode a
plain ``open`` would give under the user's umask: ``mkstemp`` makes files 0600, and USD's
writers keep the mode of the file they overwrite, which would leave a stage in a shared
folder unreadable by the rest of a cluster.
"""

from __future__ import annotations

import contextlib
import filecmp
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from regnf.core.atomic_io import TEMP_PREFIX, temp_beside, user_mode
from regnf.core.errors import RegnfError


class FileTransaction:
    """Collects temporary files and their destinations; see the module docstring."""

    def __init__(self) -> None:
        self._staged: list[tuple[Path, Path]] = []
        self._created_dirs: list[Path] = []

    def _mkdirs(self, folder: Path) -> None:
        missing = []
        p = folder
        while not p.exists():
            missing.append(p)
            p = p.parent
        for d in reversed(missing):
            d.mkdir()
            self._created_dirs.append(d)

    def temp_path(self, dest: str | os.PathLike) -> Path:
        """A new temporary file beside ``dest`` (same suffix) that will replace it on commit."""
        dest = Path(dest).absolute()
        if any(d == dest for _, d in self._staged):
            raise RegnfError(f"{dest} is written twice in one transaction")
        self._mkdirs(dest.parent)
        tmp = temp_beside(dest)
        self._staged.append((tmp, dest))
        return tmp

    def write_bytes(self, dest: str | os.PathLike, data: bytes) -> None:
        """Stage ``data`` for ``dest``."""
        with open(self.temp_path(dest), "wb") as f:
            f.write(data)

    def copy(self, src: str | os.PathLike, dest: str | os.PathLike) -> None:
        """Stage a copy of ``src`` for ``dest`` (nothing when they are the same file)."""
        src, dest = Path(src), Path(dest)
        if dest.exists() and os.path.samefile(src, dest):
            return
        shutil.copyfile(src, self.temp_path(dest))

    def abort(self) -> None:
        """Remove every temporary and every folder created; the destinations are untouched."""
        for tmp, _ in self._staged:
            tmp.unlink(missing_ok=True)
        for d in reversed(self._created_dirs):
            with contextlib.suppress(OSError):
                d.rmdir()
        self._staged.clear()
        self._created_dirs.clear()

    def commit(self) -> list[Path]:
        """Move every staged file into place (unchanged files are left alone); returns them."""
        done: list[tuple[Path, Path | None]] = []
        written: list[Path] = []
        try:
            for tmp, dest in self._staged:
                if dest.exists() and filecmp.cmp(tmp, dest, shallow=False):
                    tmp.unlink()
                    continue
                backup = None
                if dest.exists():
                    backup = Path(tempfile.mktemp(prefix=f"{TEMP_PREFIX}{dest.name}.old.", dir=dest.parent))
                    os.link(dest, backup)
                # Again here: a writer may have replaced the temporary by a file of its own mode.
                user_mode(tmp)
                os.replace(tmp, dest)
                done.append((dest, backup))
                written.append(dest)
        except BaseException:
            for dest, backup in reversed(done):
                if backup is None:
                    dest.unlink(missing_ok=True)
                else:
                    os.replace(backup, dest)
            self.abort()
            raise
        for _, backup in done:
            if backup is not None:
                backup.unlink(missing_ok=True)
        self._staged.clear()
        self._created_dirs.clear()
        return written


@contextlib.contextmanager
def file_transaction() -> Iterator[FileTransaction]:
    """``with file_transaction() as tx: ...``: commit on success, abort on any exception."""
    tx = FileTransaction()
    try:
        yield tx
    except BaseException:
        tx.abort()
        raise
    tx.commit()
