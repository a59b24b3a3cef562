"""Noticing that the stage a viewer shows was changed on disk by another program.

The stamp of a stage is what :func:`os.stat` says (file identity, size, modification time) of
its layers: the stage file, the layers of its library and slots, and, for a replacement layer,
those of the stage it sits over. regnf writes a layer to a temporary file and renames it, so
every write changes the file's identity even within one clock tick.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from regnf.scene_graph.layout import LIBRARY_DIR, SLOTS_DIR, STAGE_SUFFIXES

Stamp = tuple[tuple[str, int, int, int], ...]
"""(path, inode, size, modification time in ns) of every layer file, sorted."""


def stage_files(stage: Path, base: Path | None = None) -> list[Path]:
    """The layer files of ``stage`` (and of the stage ``base`` it replaces, if any)."""
    files: list[Path] = []
    for root in (stage, base):
        if root is None:
            continue
        files.append(root)
        for folder in (LIBRARY_DIR, SLOTS_DIR):
            d = root.parent / folder
            if d.is_dir():
                files += sorted(p for p in d.iterdir() if p.suffix in STAGE_SUFFIXES)
    return files


def stamp(stage: Path, base: Path | None = None) -> Stamp:
    """The stamp of ``stage`` now (a missing file counts as one of size -1)."""
    out = []
    for path in stage_files(stage, base):
        try:
            st = os.stat(path)
            out.append((str(path), st.st_ino, st.st_size, st.st_mtime_ns))
        except OSError:
            out.append((str(path), -1, -1, -1))
    return tuple(sorted(out))


class StageWatcher:
    """Keeps a viewer's stage current: checks its stamp on a timer and before each edit, and
    reloads it (``reload()``, which raises ``ValueError`` naming the file when the stage cannot
    be read) when another program changed it.

    Parameters
    ----------
    stage, base : Path
        The stage and the stage it replaces (None for a plain stage).
    initial : Stamp
        The stamp taken before the viewer read the stage.
    reload : callable
        Re-reads the stage and shows it; its argument says whether another program changed it
        (else the viewer wrote it).
    poll_seconds : float
        Time between two checks on the timer.
    """

    def __init__(self, stage: Path, base: Path | None, initial: Stamp, reload: Callable[[bool], None],
                 poll_seconds: float) -> None:
        self.stage, self.base, self.stamp = stage, base, initial
        self.lock = threading.RLock()
        """Held while the stage is checked, reloaded or written by the viewer."""
        self.error: str | None = None
        """Why the stage on disk cannot be read now (edits wait), or None."""
        self.reloads = 0
        """How many times a change on disk was loaded."""
        self._reload, self._poll = reload, poll_seconds
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="regnf-view-stage", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30.0)

    def sync(self) -> bool:
        """Reload the stage if its files changed since it was read; whether they had."""
        with self.lock:
            now = stamp(self.stage, self.base)
            if now == self.stamp:
                return False
            self.stamp = now
            self._load(True)
            return True

    @contextlib.contextmanager
    def writing(self) -> Iterator[None]:
        """Around the viewer's own write: the stage is reloaded after it, and not counted as a
        change made by another program."""
        with self.lock:
            yield
            self.stamp = stamp(self.stage, self.base)
            self._load(False)

    def _load(self, other: bool) -> None:
        try:
            self._reload(other)
        except (ValueError, OSError) as exc:  # a stage being edited by hand, say: kept until it reads
            self.error = " ".join(str(exc).split())
        else:
            self.error = None
            self.reloads += 1

    def _loop(self) -> None:
        while not self._stop.wait(self._poll):
            try:
                self.sync()
            except Exception as exc:  # noqa: BLE001 (the next tick retries; the viewer keeps running)
                self.error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
