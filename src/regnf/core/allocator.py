"""Keep freed memory for reuse: glibc's allocator tuned for training's large per-step buffers.

Every training step frees and allocates again the gradient of each dense feature grid (tens
of megabytes for a room). glibc serves allocations that large with a fresh ``mmap`` and
returns them to the system on free, so every step zero-fills pages the kernel must fault in
one by one, a large share of a room's training step (docs/decisions/implementation-speed.md).
This module makes glibc keep its freed memory in the heap instead, for the rest of the process.

The price is that a process does not give memory back to the system before it exits, so its
resident size stays at its peak. That is right for a command (``regnf`` calls
:func:`keep_freed_memory` at start) and is left to the caller in a library setting.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1
"""glibc's ``mallopt`` parameter: free memory at the heap's top kept before trimming."""
M_MMAP_MAX = -4
"""glibc's ``mallopt`` parameter: how many allocations may be served by ``mmap`` (0: none)."""


def keep_freed_memory() -> bool:
    """Make glibc's ``malloc`` serve every allocation from the heap and never trim it.

    Returns
    -------
    bool
        Whether it took effect (False where the C library is not glibc, e.g. macOS, musl).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # The largest int: the heap's free top is never handed back while the process runs.
    trimmed = mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    no_mmap = mallopt(M_MMAP_MAX, 0)
    return bool(trimmed and no_mmap)
