"""Exclusive locks between processes that write the same stage or output folder.

A lock is a POSIX record lock (``fcntl.lockf``) on a small hidden file beside what it
protects, e.g. ``.regnf.lock`` in a stage's folder. Record locks are released by the kernel
when the holding process dies (a ``kill -9`` leaves no stale lock), and they are the kind of
lock NFS forwards to the server (NFSv4, or NFSv3 with ``lockd``), so two machines of a Ray
cluster writing into one shared folder exclude each other too. On a file system that cannot
lock (some SMB and FUSE mounts) taking the lock fails with :class:`LockUnavailable` rather
than going on unprotected.

The lock file is left in place after use: removing it would let a third process lock a new
file while a second still waits on the old one. It holds the pid and host of the last
holder, which the "busy" message quotes.

Record locks belong to a process, not to a file descriptor, so within one process a
registry of held paths stands in for them: a second ``with file_lock(p)`` in another thread
waits for the first, as another process would, and one in the same thread (a command that
holds its output folder and calls a writer that locks the same folder) simply nests.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

LOCK_NAME = ".regnf.lock"
"""File name of the lock that guards a folder (a stage's folder, an output folder)."""
POLL_SECONDS = 0.05
"""How often a waiting writer tries again."""

_held: dict[str, threading.Lock] = {}
_registry_guard = threading.Lock()
_this_thread = threading.local()


class LockBusy(RuntimeError):
    """Another process holds the lock (and the wait, if any, ran out); names the lock file."""

    def __init__(self, path: Path, what: str, holder: str) -> None:
        self.path = path
        self.holder = holder
        super().__init__(f"{path}: {what} is in use by another regnf process ({holder or 'unknown holder'}); "
                         "wait for it to finish, or use another folder")


class LockUnavailable(OSError):
    """The file system of the lock file cannot take locks; names the file."""

    def __init__(self, path: Path, reason: str) -> None:
        self.path = path
        super().__init__(f"{path}: cannot take a file lock here ({reason}); this file system does not "
                         "support POSIX locks (use a local folder, or NFS with locking enabled)")


def _thread_lock(key: str) -> threading.Lock:
    with _registry_guard:
        return _held.setdefault(key, threading.Lock())


def _held_here() -> set[str]:
    """Keys of the locks the calling thread holds."""
    if not hasattr(_this_thread, "keys"):
        _this_thread.keys = set()
    return _this_thread.keys


def _read_holder(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        return os.read(fd, 200).decode("utf-8", "replace").strip()
    except OSError:
        return ""


@contextlib.contextmanager
def file_lock(lock_path: str | os.PathLike, what: str = "this folder", timeout: float = 0.0) -> Iterator[Path]:
    """Hold an exclusive lock on ``lock_path`` (created if missing) for the block.

    Parameters
    ----------
    lock_path : str or PathLike
        The lock file; its folder must exist.
    what : str
        What the lock guards, for the message (``"the stage"``, ``"the output folder"``).
    timeout : float
        Seconds to wait for another holder; 0 fails at once, ``inf`` waits for ever.

    The lock nests: a thread that holds it already enters at once (and keeps it until its
    outermost block ends).

    Raises
    ------
    LockBusy
        Another process (or thread) still holds it after ``timeout``.
    LockUnavailable
        The file system does not support locks.
    """
    path = Path(lock_path).absolute()
    key = os.path.realpath(path)
    if key in _held_here():
        yield path
        return
    deadline = time.monotonic() + timeout
    local = _thread_lock(key)
    if not local.acquire(timeout=-1 if timeout == float("inf") else max(0.0, timeout)):
        raise LockBusy(path, what, "another thread of this process")
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            while True:
                try:
                    fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EACCES):
                        raise LockUnavailable(path, exc.strerror or str(exc)) from exc
                    if time.monotonic() >= deadline:
                        raise LockBusy(path, what, _read_holder(fd)) from None
                    time.sleep(POLL_SECONDS)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
            _held_here().add(key)
            try:
                yield path
            finally:
                _held_here().discard(key)
                fcntl.lockf(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)
    finally:
        local.release()


def folder_lock(folder: str | os.PathLike, what: str = "this folder", timeout: float = 0.0):
    """:func:`file_lock` on ``folder/.regnf.lock`` (the folder must exist)."""
    return file_lock(Path(folder) / LOCK_NAME, what, timeout)
