"""An output folder a command owns: claimed before any work, marked, and cleaned only of its own.

A command that writes a folder of results (``regnf generate``, ``regnf demo``) claims it
first with :func:`claim_output_dir`. The folder is accepted if it does not exist (it is
made), is empty, or carries the marker of the same kind of command; anything else (a
folder of the user's, the output of another command) is refused with an
:class:`OutputFolderError` before anything is written, unless the caller passes
``reuse=True`` (the user's explicit consent: the command then adds its files there and
still never removes what it did not make).

The marker, ``.regnf-output.json``, is written atomically. It names the kind of command
and the top-level entries the command made there (:meth:`OutputFolder.reserve`); only those
may be removed (:meth:`OutputFolder.remove`). Its content holds no time or path, so two
runs that make the same files write the same marker.

Temporary entries (staging folders, files being written) are named with
:data:`regnf.core.atomic_io.TEMP_PREFIX`. One still there after a run was left by a killed
run: it is ours to remove, and nothing without that prefix ever is. Every writer that
makes such entries in a folder holds the folder's lock (:mod:`regnf.core.file_lock`) while
they exist, so :func:`remove_leftovers`, called under the same lock, never removes a live
one. :func:`owned_output_dir` does all of it: claim, lock, clean, yield.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from regnf.core.atomic_io import TEMP_PREFIX, user_mode, write_json
from regnf.core.errors import RegnfError
from regnf.core.file_lock import LOCK_NAME, folder_lock
from regnf.core.preflight import JsonInputError, read_json_input

MARKER_NAME = ".regnf-output.json"
"""File name of the marker that says which kind of command made a folder, and what it made there."""
MARKER_FORMAT = 1
"""Version of the marker's content."""
REUSE_ADVICE = ("choose a new or empty folder, or reuse this one explicitly (reuse=True; on the command "
                "line --reuse): regnf then adds its files and removes nothing it did not make")
"""What to do about a folder that is refused because it holds foreign files."""

class OutputFolderError(RegnfError):
    """An output folder cannot be used as asked; the message names it and says what to do.

    Parameters
    ----------
    path : Path
        The folder (or the entry in it) that is the problem.
    problem : str
        What is wrong with it.
    advice : str
        What the user can do.
    """

    def __init__(self, path: Path, problem: str, advice: str) -> None:
        self.path = path
        super().__init__(f"{path}: {problem}; {advice}")


def is_ours(name: str) -> bool:
    """Whether a folder entry named ``name`` is regnf's bookkeeping (marker, lock, temporaries), not content."""
    return name in (MARKER_NAME, LOCK_NAME) or name.startswith(TEMP_PREFIX)


def foreign_entries(folder: Path) -> list[str]:
    """Names of the entries of ``folder`` that are not regnf's bookkeeping, sorted (empty if no folder)."""
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if not is_ours(p.name))


def _describe(names: Sequence[str], limit: int = 3) -> str:
    shown = ", ".join(names[:limit])
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return f"{len(names)} entr{'y' if len(names) == 1 else 'ies'}: {shown}{more}"


def read_marker(folder: Path) -> dict[str, Any] | None:
    """The marker of ``folder`` (None if it has none).

    Raises
    ------
    OutputFolderError
        The marker exists but is not one regnf wrote (unreadable, not JSON, wrong keys).
    """
    path = folder / MARKER_NAME
    if not path.exists():
        return None
    try:
        marker = read_json_input(path, None, "output marker")
    except JsonInputError as exc:
        raise OutputFolderError(path, f"unreadable output marker ({exc.problem})",
                                "remove it if the folder is yours, or choose another folder") from exc
    entries = marker.get("entries") if isinstance(marker, dict) else None
    if (not isinstance(marker, dict) or not isinstance(marker.get("kind"), str)
            or not isinstance(entries, list) or not all(isinstance(e, str) for e in entries)):
        raise OutputFolderError(path, "not a regnf output marker (it needs 'kind' and 'entries')",
                                "remove it if the folder is yours, or choose another folder")
    return marker


def _marker(kind: str, entries: Iterable[str]) -> dict[str, Any]:
    return {"made_by": "regnf", "kind": kind, "format": MARKER_FORMAT, "entries": sorted(set(entries))}


@dataclass(frozen=True)
class OutputFolder:
    """A claimed output folder (see the module).

    Change it (:meth:`reserve`, :meth:`remove`) only while holding its lock, as
    :func:`owned_output_dir` does.
    """

    path: Path
    """The folder, absolute."""
    kind: str
    """The kind of command that owns it (``"generate"``, ``"demo"``)."""
    entries: frozenset[str]
    """Top-level entries the command recorded as made by it."""

    def owns(self, name: str) -> bool:
        """Whether the top-level entry ``name`` was recorded as made by this kind of command."""
        return name in self.entries

    def unowned(self, names: Iterable[str]) -> list[str]:
        """Those of the top-level ``names`` that exist and were not made by this kind of command, sorted."""
        return sorted(n for n in set(names) - self.entries if os.path.lexists(self.path / n))

    def require_free(self, names: Iterable[str]) -> None:
        """Refuse if one of the top-level ``names`` exists and was not made by this kind of command.

        Raises
        ------
        OutputFolderError
            Naming the first such entry.
        """
        for name in self.unowned(names):
            raise OutputFolderError(self.path / name, f"exists and was not made by regnf {self.kind}",
                                    "move it away, or choose another output folder")

    def reserve(self, names: Iterable[str]) -> OutputFolder:
        """Record the top-level ``names`` this command is about to write; return the updated folder.

        Raises
        ------
        OutputFolderError
            One of them exists and was not made by this kind of command (it is the user's);
            nothing is recorded then.
        """
        names = set(names)
        self.require_free(names)
        if names <= self.entries:
            return self
        entries = self.entries | names
        write_json(self.path / MARKER_NAME, _marker(self.kind, entries))
        return OutputFolder(self.path, self.kind, frozenset(entries))

    def remove(self, name: str) -> None:
        """Remove the top-level entry ``name`` (a folder with all it holds), which must be recorded as ours.

        Raises
        ------
        OutputFolderError
            ``name`` is not recorded as made by this kind of command.
        """
        if not self.owns(name):
            raise OutputFolderError(self.path / name, f"was not made by regnf {self.kind}, so it is not removed",
                                    "remove it yourself if it should go")
        _remove(self.path / name)


def _remove(path: Path) -> None:
    """Remove a file, a link (not what it points to) or a folder tree; nothing if it is gone."""
    if path.is_symlink() or not path.is_dir():
        path.unlink(missing_ok=True)
    else:
        shutil.rmtree(path, ignore_errors=True)


def inspect_output_dir(out: str | os.PathLike, kind: str, reuse: bool = False) -> OutputFolder:
    """What :func:`claim_output_dir` would accept, without writing anything; raises as it does."""
    path = Path(out).absolute()
    if os.path.lexists(path) and not path.is_dir():
        raise OutputFolderError(path, "exists and is not a folder", "choose a folder")
    marker = read_marker(path)
    if marker is not None:
        if marker["kind"] != kind:
            raise OutputFolderError(path, f"holds the output of regnf {marker['kind']}",
                                    f"choose another folder for regnf {kind}")
        return OutputFolder(path, kind, frozenset(marker["entries"]))
    foreign = foreign_entries(path)
    if foreign and not reuse:
        raise OutputFolderError(path, f"is not empty and was not made by regnf {kind} (it holds {_describe(foreign)})",
                                REUSE_ADVICE)
    return OutputFolder(path, kind, frozenset())


def claim_output_dir(out: str | os.PathLike, kind: str, reuse: bool = False) -> OutputFolder:
    """Claim ``out`` for a command of ``kind``: make it, or accept it if it may be written (see the module).

    Nothing is written when the folder is refused. An accepted folder without a marker gets
    one (and keeps everything it holds).

    Parameters
    ----------
    out : str or PathLike
        The output folder (made with its parents if missing).
    kind : str
        The kind of command, e.g. ``"generate"``; the marker records it.
    reuse : bool
        Accept a folder that holds entries this kind of command did not make (the user's
        explicit consent); a folder marked by another kind of command is refused even then.

    Returns
    -------
    OutputFolder

    Raises
    ------
    OutputFolderError
        ``out`` is a file, is marked by another kind of command, has an unreadable marker,
        or holds foreign entries and ``reuse`` is False.
    """
    folder = inspect_output_dir(out, kind, reuse)
    if not (folder.path / MARKER_NAME).exists():
        folder.path.mkdir(parents=True, exist_ok=True)
        write_json(folder.path / MARKER_NAME, _marker(kind, folder.entries))
    return folder


def replace_entry(src: str | os.PathLike, dest: str | os.PathLike) -> None:
    """Rename ``src`` (a file or a folder) to ``dest``, replacing what ``dest`` is.

    The caller has established that ``dest`` is its own. The old ``dest`` is first renamed
    aside to a ``.regnf-tmp-*`` name and removed after the rename, so ``dest`` is at every
    moment the old entry or the new one; a kill in between leaves only a leftover that the
    next run removes.
    """
    src, dest = Path(src), Path(dest)
    if not os.path.lexists(dest):
        os.replace(src, dest)
        return
    aside = Path(tempfile.mkdtemp(prefix=staging_prefix(f"old-{dest.name}"), dir=dest.parent))
    old = aside / dest.name
    os.replace(dest, old)
    os.replace(src, dest)
    _remove(aside)


def staging_prefix(label: str) -> str:
    """Name prefix of the staging folders :func:`make_staging_dir` makes for ``label``."""
    return f"{TEMP_PREFIX}{label}-"


def make_staging_dir(parent: str | os.PathLike, label: str) -> Path:
    """A new, empty staging folder in ``parent``, named ``.regnf-tmp-<label>-<random>``.

    It gets the permissions a plain ``mkdir`` would (``mkdtemp`` makes it 0700), so that
    once renamed into place it reads as the user's umask says. The caller must hold
    ``parent``'s lock while it exists (see the module), and rename or remove it.
    """
    path = Path(tempfile.mkdtemp(prefix=staging_prefix(label), dir=parent))
    user_mode(path, directory=True)
    return path


@contextlib.contextmanager
def staging_dir(parent: str | os.PathLike, label: str) -> Iterator[Path]:
    """:func:`make_staging_dir` for the block; removed at its end unless it was renamed away."""
    path = make_staging_dir(parent, label)
    try:
        yield path
    finally:
        if path.exists():
            shutil.rmtree(path, ignore_errors=True)


def remove_leftovers(folder: str | os.PathLike, prefix: str = TEMP_PREFIX, recursive: bool = False) -> list[Path]:
    """Remove the entries of ``folder`` whose names start with ``prefix``: what killed runs left.

    Call it only while holding ``folder``'s lock (a live run's temporaries are then not
    there). Links are removed, never followed.

    Parameters
    ----------
    folder : str or PathLike
        Where to look; nothing happens if it does not exist.
    prefix : str
        Names to remove; it must start with :data:`TEMP_PREFIX` (nothing else is ours to remove).
    recursive : bool
        Also look in every subfolder (not those removed, not through links).

    Returns
    -------
    list of Path
        What was removed.
    """
    if not prefix.startswith(TEMP_PREFIX):
        raise RegnfError(f"only entries named {TEMP_PREFIX}* are removed, got prefix {prefix!r}")
    removed: list[Path] = []
    root = Path(folder)
    if not root.is_dir():
        return removed
    pending = [root]
    while pending:  # a walk that prunes what it removes
        here = pending.pop()
        with os.scandir(here) as it:
            entries = list(it)
        for entry in entries:
            path = Path(entry.path)
            if entry.name.startswith(prefix):
                _remove(path)
                removed.append(path)
            elif recursive and entry.is_dir(follow_symlinks=False):
                pending.append(path)
    return removed


@contextlib.contextmanager
def owned_output_dir(out: str | os.PathLike, kind: str, reuse: bool = False, what: str = "the output folder",
                     ) -> Iterator[OutputFolder]:
    """Claim ``out`` (:func:`claim_output_dir`), hold its lock for the block, and first remove leftovers.

    Parameters
    ----------
    out, kind, reuse
        As for :func:`claim_output_dir`.
    what : str
        What the folder is, for the "busy" message.

    Yields
    ------
    OutputFolder

    Raises
    ------
    OutputFolderError
        The folder is refused (nothing written), or another kind of command marked it
        between the claim and the lock.
    regnf.core.file_lock.LockBusy
        Another process holds the folder's lock: it is writing there now.
    regnf.core.file_lock.LockUnavailable
        The folder's file system cannot take locks.
    """
    folder = claim_output_dir(out, kind, reuse)
    with folder_lock(folder.path, what):
        # Claims are made before the lock (a refused folder must not get a lock file); a
        # claimer of another kind may have marked the folder in between.
        marker = read_marker(folder.path)
        if marker is None or marker["kind"] != kind:
            found = "no marker" if marker is None else f"the marker of regnf {marker['kind']}"
            raise OutputFolderError(folder.path, f"was claimed for regnf {kind} but now holds {found}",
                                    "another command is using it; choose another folder")
        folder = OutputFolder(folder.path, kind, frozenset(marker["entries"]))
        remove_leftovers(folder.path)
        yield folder
