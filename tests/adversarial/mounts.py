"""Small file systems for the tests of refused writes: read-only, or nearly full."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def tmpfs(folder: Path, options: str) -> Iterator[Path]:
    """Mount a tmpfs with ``options`` (``"ro,size=64k"``) on the existing ``folder`` for the block.

    Skips the test where it cannot mount (not root, or no mount rights in the container).
    """
    if os.geteuid() != 0:
        pytest.skip("mounting a small file system needs root")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                          capture_output=True, check=False)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({made.stderr.decode().strip()})")
    try:
        yield folder
    finally:
        # Lazily: a file mapped by this process (a loaded checkpoint) keeps the mount busy until freed.
        subprocess.run(["umount", "--lazy", str(folder)], check=True)
