"""keep_freed_memory: large allocations come from the heap, not from mmap, afterwards."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# Run in a child process: the setting lasts for the process, and the test suite's own process
# should keep the allocator it started with. mallinfo2 (glibc >= 2.33) counts the blocks that
# are mmap-ed (hblks): a 64 MB buffer adds one with glibc's defaults, none after the call.
CHILD = textwrap.dedent(
    """
    import ctypes, ctypes.util, sys
    from regnf.core.allocator import keep_freed_memory

    class MallInfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
            "fordblks", "keepcost")]

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    if not hasattr(libc, "mallinfo2"):
        print("no-mallinfo2"); sys.exit(0)
    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]

    def mmapped_while_holding(nbytes):  # blocks mmap-ed by this one allocation
        before = libc.mallinfo2().hblks
        p = libc.malloc(nbytes)
        hblks = libc.mallinfo2().hblks - before
        libc.free(p)
        return hblks

    before = mmapped_while_holding(64 << 20)
    applied = keep_freed_memory()
    after = mmapped_while_holding(64 << 20)
    print(before, applied, after)
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_large_buffers_come_from_the_heap_after_the_call() -> None:
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True).stdout
    if out.strip() == "no-mallinfo2":
        pytest.skip("this C library has no mallinfo2")
    before, applied, after = out.split()
    assert (int(before), applied, int(after)) == (1, "True", 0)
