"""Folder locks: another process or thread is kept out (or waits), the same thread nests."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from regnf.core.file_lock import LOCK_NAME, LockBusy, folder_lock

ROOT = Path(__file__).parents[2]


def _hold_in_a_process(folder: Path, seconds: float) -> subprocess.Popen:
    code = ("import sys, time\nfrom regnf.core.file_lock import folder_lock\n"
            f"with folder_lock({str(folder)!r}):\n    print('held', flush=True)\n    time.sleep({seconds})")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_another_process_is_refused_then_waited_for(tmp_path: Path) -> None:
    proc = _hold_in_a_process(tmp_path, 1.0)
    try:
        busy = rf"{LOCK_NAME}: the stage is in use by another regnf process \(pid {proc.pid}"
        with pytest.raises(LockBusy, match=busy), folder_lock(tmp_path, "the stage"):
            pass
        t0 = time.monotonic()
        with folder_lock(tmp_path, timeout=30.0):  # entered once the holder lets go, a second later
            waited = time.monotonic() - t0
        assert waited > 0.3
    finally:
        proc.kill()
        proc.wait()


def test_the_same_thread_nests_and_another_thread_is_kept_out(tmp_path: Path) -> None:
    seen: list[str] = []

    def other() -> None:
        try:
            with folder_lock(tmp_path):
                seen.append("entered")
        except LockBusy:
            seen.append("busy")

    with folder_lock(tmp_path), folder_lock(tmp_path):  # nested: no deadlock, no error
        t = threading.Thread(target=other)
        t.start()
        t.join()
    assert seen == ["busy"]
    t = threading.Thread(target=other)  # released by the outer block only
    t.start()
    t.join()
    assert seen == ["busy", "entered"]
