"""Denormal floats flushed to zero around the networks' evaluations: the CPU's fast mode.

The SDF network's activation is a softplus of sharpness 100 (NeuS), ``log1p(exp(100 h)) / 100``.
Its ``log1p`` of the small ``exp(100 h)`` of most pre-activations squares them into denormal
floats (below 1.2e-38) on the way, and an x86 CPU computes with those many times slower than
with normal ones: on one thread, a softplus over 65536 x 64 normal-distributed values takes
76 ms, against 9 ms with denormals flushed to zero (and 6 ms for sharpness 1). Flushed, the
renders and the distances, gradients and colours of the demo's fields are the same bits
(tested on a field whose softplus meets denormals).

The mode is a register of each CPU thread, so it is set for the span of an evaluation on the
calling thread only (:func:`denormals_flushed`), not for the process: code that is not ours
breaks in it (SciPy's k-d tree over FPFH features recurses without end on denormal
differences, and the process dies). Torch's own worker threads keep the default mode: with one
thread per evaluation, as the renders, the bakes and the registrations run, all of it is
flushed.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import torch

_state = threading.local()
_PROBE = -100.0
"""exp of it is denormal (3.7e-44), or zero in the flushing mode."""


def flushing() -> bool:
    """Whether this thread computes with denormal floats as zero."""
    return float(torch.exp(torch.tensor(_PROBE, device="cpu"))) == 0.0  # the CPU's mode, whatever the default device


@contextlib.contextmanager
def denormals_flushed() -> Iterator[None]:
    """Run the block with denormal floats flushed to zero on this thread; the thread's mode
    before it comes back after it (the block may nest)."""
    depth = getattr(_state, "depth", 0)
    restore = depth == 0 and not flushing()
    if restore:
        torch.set_flush_denormal(True)
    _state.depth = depth + 1
    try:
        yield
    finally:
        _state.depth = depth
        if restore:
            torch.set_flush_denormal(False)
