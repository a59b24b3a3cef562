"""Denormal floats flushed to zero around the networks' evaluations: the CPU's fast mode.

The SDF network's activation is a softplus of sharpness 100 (NeuS), ``log1p(exp(100 h)) / 100``.
Its ``log1p`` of the small ``exp(100 h)`` of most pre-activations squares them into denormal
floats (below 1.2e-38) on the way, and an x86 CPU computes with those many times slower than
with normal ones (docs/decisions/implementation-speed.md). Flushed, the renders and the
distances, gradients and colours of the demo's fields are the same bits
(tested on a field whose softplus meets denormals).

The mode is a register of each CPU thread, so it is set for the span of an evaluation on the
calling thread only (:func:`denormals_flushed`), not for the process: code that is not ours
breaks in it (SciPy's k-d tree over FPFH features recurses without end on denormal
differences, and the process dies). Torch's own worker threads keep the default mode: with one
thread per evaluation, as the renders, the bakes and the registrations run, all of it is
flushed. Training runs its kernels on torch's threads and its backward outside the
evaluations, so its loop sets the mode on every thread of torch's OpenMP pool as well, for the
loop's span only (:func:`pool_denormals_flushed`).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading
from collections.abc import Callable, Iterator

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


_GOMP_BODY = ctypes.CFUNCTYPE(None, ctypes.c_void_p)


def _openmp_runtime() -> ctypes.CDLL | None:
    """The GNU OpenMP runtime torch runs its CPU kernels on (loaded in this process), or None
    (another runtime, or not Linux)."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "libgomp" in line.rsplit("/", 1)[-1]}
    except OSError:
        return None
    torch_dir = os.path.dirname(torch.__file__)
    for path in sorted(paths, key=lambda p: (not p.startswith(torch_dir), p)):  # torch's own first
        try:
            lib = ctypes.CDLL(path)  # already loaded: the same handle, not a second runtime
            lib.GOMP_parallel.argtypes = [_GOMP_BODY, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint]
            lib.GOMP_parallel.restype = None
            return lib
        except (OSError, AttributeError):
            continue
    return None


def _on_every_pool_thread(body: Callable[[], None]) -> bool:
    """Run ``body`` once on each thread of the OpenMP team torch's kernels use from this thread
    (this thread is one of them); False where that runtime is not found."""
    lib = _openmp_runtime()
    if lib is None:
        return False
    errors: list[BaseException] = []

    def run(_: int | None) -> None:  # on an OpenMP thread; ctypes takes the interpreter lock
        try:
            body()
        except BaseException as exc:  # noqa: BLE001 - re-raised on the calling thread
            errors.append(exc)

    callback = _GOMP_BODY(run)  # kept alive for the call
    lib.GOMP_parallel(callback, None, max(1, torch.get_num_threads()), 0)
    if errors:
        raise errors[0]
    return True


@contextlib.contextmanager
def pool_denormals_flushed() -> Iterator[None]:
    """Run the block with denormal floats flushed to zero on this thread and on every thread of
    torch's OpenMP pool (its intra-op kernels run there); after it, the pool's threads are in
    the default mode (whatever they had before: a pool thread started inside a flushed
    evaluation copies its mode) and this thread in its earlier one.

    For training loops, which run nothing but torch: the same bits as without (the softplus's
    denormals only ever round away; tested), and faster (docs/decisions/implementation-speed.md).
    Where torch's OpenMP runtime
    cannot be reached (not GNU OpenMP, not Linux), only this thread's mode is set.
    """
    with denormals_flushed():
        pooled = _on_every_pool_thread(lambda: torch.set_flush_denormal(True))
        try:
            yield
        finally:
            if pooled:
                # Every pool thread back to the default; this one is restored by the outer block.
                _on_every_pool_thread(lambda: torch.set_flush_denormal(False))
                torch.set_flush_denormal(True)
