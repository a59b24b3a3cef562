"""``regnf bench capture-scale``: time and peak memory of sample building and training against
the number of frames of a capture.

A synthetic room capture with many frames at a depth sensor's size (default 600 frames of
640 x 480 on the full-coverage trajectory, every frame a training frame) is made once in the
cache. Then, each in a process of its own so that its peak resident memory is that run's alone:

- :func:`regnf.observations.rgbd_samples.build_samples` on the first N frames, for each N;
- :func:`regnf.training.training.train_rgbd` with the room preset on the first
  ``train_frames`` frames (sample building included), after the memory check ``regnf train``
  makes (:func:`regnf.observations.sample_memory.check_training_memory`).

The child process (``python -m regnf.benchmarks.capture_scale CAPTURE STAGE FRAMES``) prints
one JSON line: its wall seconds, its peak resident memory (``getrusage(RUSAGE_SELF).ru_maxrss``)
and the resident memory it had before the measured call (the interpreter, torch and the
capture's metadata). Its address space is capped at :data:`LIMIT_SHARE` of the memory
available when it starts (``RLIMIT_AS``), so that a run too large for the machine fails in its own allocation, reported
as ``out_of_memory``, instead of waking the kernel's out-of-memory killer on a shared machine.
A run that regnf refuses before its long work (a ``ValueError`` such as the memory check's
:class:`~regnf.core.preflight.PreflightError`) is reported with the refusal's line and, for the
memory check, the smallest pixel stride that check would accept (:func:`fitting_stride`); one
that dies otherwise with its exit status and the peak the parent's ``wait4`` saw.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from tqdm import tqdm

STAGES = ("build_samples", "train")
"""What a child process measures."""

KIB_PER_GIB = 2**20
"""``ru_maxrss`` is in KiB on Linux."""

LIMIT_SHARE = 0.9
"""Default address-space cap of a run, as a share of the memory available when it starts (the
rest is left to the machine's other processes)."""

MAX_STRIDE = 16
"""Largest pixel stride :func:`fitting_stride` tries."""


def fitting_stride(n_frames: int, height: int, width: int, free_bytes: int) -> int | None:
    """The smallest pixel stride at which training ``n_frames`` frames of ``width x height`` fits
    in ``free_bytes`` by the memory check's own estimate
    (:func:`regnf.observations.sample_memory.training_bytes`); None when none up to :data:`MAX_STRIDE` does."""
    from regnf.observations.sample_memory import training_bytes

    return next((s for s in range(1, MAX_STRIDE + 1) if training_bytes(n_frames, height, width, s) <= free_bytes),
                None)


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / KIB_PER_GIB


def measure(capture_dir: Path, stage: str, frames: int, device: str = "cpu", steps: int = 0,
            pixel_stride: int = 1) -> dict:
    """Run ``stage`` on the first ``frames`` training frames of the capture, in this process.

    Training runs after the memory check ``regnf train`` makes
    (:func:`regnf.observations.sample_memory.check_training_memory`); sample building alone
    runs unchecked (the address-space cap of :func:`run_child` stops it).

    Parameters
    ----------
    capture_dir : Path
        A capture folder (sdfstudio layout, as the cache writes it).
    stage : str
        ``build_samples`` or ``train`` (:data:`STAGES`).
    frames : int
        How many of the capture's first training frames.
    device : str
        Torch device of the training.
    steps : int
        Training steps; 0: the room preset's.
    pixel_stride : int
        Samples from every ``pixel_stride``-th row and column.

    Returns
    -------
    dict
        ``stage``, ``frames``, ``pixel_stride``, ``status`` (``ok``, ``refused`` or
        ``out_of_memory``), ``seconds``, ``peak_rss_gib``, ``start_rss_gib`` (the peak before the
        measured call), ``estimated_gib`` (the memory check's estimate: of the training, or of
        the sample building's peak), ``samples`` (surface points built; ``build_samples``) or
        ``steps`` (``train``), and for a run that did not finish its ``message`` (and a
        memory check's refusal's ``suggested_stride``: :func:`fitting_stride`).
    """
    from regnf.captures.sdfstudio import load_capture
    from regnf.core.preflight import available_memory_bytes
    from regnf.observations.rgbd_samples import build_samples
    from regnf.observations.sample_memory import (
        BUILD_PEAK,
        check_training_memory,
        sample_bytes,
        training_bytes,
    )
    from regnf.training.presets import scene_rgbd_preset
    from regnf.training.training import train_rgbd

    row: dict = {"stage": stage, "frames": frames, "pixel_stride": pixel_stride, "status": "ok"}
    t0 = time.perf_counter()
    try:
        capture = load_capture(capture_dir)
        indices = capture.train_indices()[:frames]
        size = (len(indices), capture.height, capture.width, pixel_stride)
        estimate = training_bytes(*size) if stage == "train" else BUILD_PEAK * sample_bytes(*size)
        row.update(frames=len(indices), start_rss_gib=_peak_gib(), estimated_gib=estimate / 2**30)
        t0 = time.perf_counter()
        if stage == "build_samples":
            row["samples"] = int(build_samples(capture, indices, pixel_stride).points.shape[0])
        else:
            try:
                check_training_memory(str(capture.root), *size)
            except ValueError:
                row["suggested_stride"] = fitting_stride(*size[:3], available_memory_bytes())
                raise
            config = dataclasses.replace(scene_rgbd_preset(device), pixel_stride=pixel_stride)
            config = dataclasses.replace(config, steps=steps) if steps > 0 else config
            _, log = train_rgbd(capture, config, indices=indices, progress=False)
            row["steps"] = log.steps
    except ValueError as exc:  # regnf's one-line refusal (memory check, bad input)
        row.update(status="refused", message=" ".join(str(exc).split()))
    except MemoryError as exc:  # numpy's allocation beyond the address-space cap
        row.update(status="out_of_memory", message=" ".join(str(exc).split()) or "MemoryError")
    except RuntimeError as exc:
        if "allocate" not in str(exc):  # torch's allocation failure; anything else is a bug
            raise
        row.update(status="out_of_memory", message=" ".join(str(exc).split()))
    row.update(seconds=time.perf_counter() - t0, peak_rss_gib=_peak_gib())
    return row


def run_child(capture_dir: Path, stage: str, frames: int, device: str = "cpu", steps: int = 0,
              memory_limit_gib: float = 0.0, pixel_stride: int = 1) -> dict:
    """:func:`measure` in a process of its own; a child that dies gives a ``failed`` row.

    ``memory_limit_gib`` caps the child's address space (0: :data:`LIMIT_SHARE` of the memory
    available now).

    Returns
    -------
    dict
        The child's row; or ``status`` ``failed`` with ``exit_status`` (negative: killed by that
        signal), ``message`` (the last line it wrote on stderr) and ``peak_rss_gib`` from ``wait4``;
        either with ``memory_limit_gib``, the cap it ran under.
    """
    from regnf.core.preflight import available_memory_bytes

    limit = memory_limit_gib or LIMIT_SHARE * available_memory_bytes() / 2**30
    cmd = [sys.executable, "-m", "regnf.benchmarks.capture_scale", str(capture_dir), stage, str(frames),
           "--device", device, "--steps", str(steps), "--memory-limit-gib", f"{limit:.3f}",
           "--pixel-stride", str(pixel_stride)]
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err)
        out = proc.stdout.read().decode(errors="replace")
        proc.stdout.close()
        # wait4, not wait: the child's own resource usage, also when it was killed.
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        stderr = err.read().decode(errors="replace").strip().splitlines()
    lines = [line for line in out.splitlines() if line.strip()]
    if proc.returncode == 0 and lines:
        return {**json.loads(lines[-1]), "memory_limit_gib": limit}
    return {"stage": stage, "frames": frames, "pixel_stride": pixel_stride, "status": "failed",
            "exit_status": proc.returncode,
            "message": stderr[-1] if stderr else "", "seconds": None,
            "peak_rss_gib": usage.ru_maxrss / KIB_PER_GIB, "memory_limit_gib": limit}


def check_plan(frames: tuple[int, ...], width: int, height: int, train_frames: int, steps: int,
               memory_limit_gib: float = 0.0, pixel_stride: int = 1) -> None:
    """Refuse, before any capture is made, counts and sizes that make no run.

    Raises
    ------
    PreflightError
        A frame count below 1, no frame count and no training run, an image side below 8
        pixels, a negative ``train_frames``, ``steps`` or ``memory_limit_gib``, or a
        ``pixel_stride`` below 1.
    """
    from regnf.core.preflight import PreflightError

    if any(n < 1 for n in frames):
        raise PreflightError(f"--frames {' '.join(map(str, frames))}: every count must be at least 1")
    if not frames and train_frames == 0:
        raise PreflightError("--frames (none) and --train-frames 0: nothing to measure")
    if width < 8 or height < 8:
        raise PreflightError(f"--width/--height {width} x {height}: each side must be at least 8 pixels")
    if train_frames < 0 or steps < 0 or not memory_limit_gib >= 0:
        raise PreflightError(f"--train-frames {train_frames} / --steps {steps} / --memory-limit-gib "
                             f"{memory_limit_gib:g}: must not be negative")
    if pixel_stride < 1:
        raise PreflightError(f"--pixel-stride {pixel_stride}: must be at least 1")


def run_capture_scale(cache, room: str = "ac-room", frames: tuple[int, ...] = (100, 300, 600), width: int = 640,
                      height: int = 480, train_frames: int = 600, device: str = "cpu", steps: int = 0,
                      memory_limit_gib: float = 0.0, pixel_stride: int = 1,
                      on_row: Callable[[dict], None] | None = None) -> dict:
    """Make (or reuse) the capture and measure every run (see the module).

    Parameters
    ----------
    cache : regnf.synthetic.cache.Cache
        Where the capture is made (its ``size`` applies: keep it ``full``).
    room : str
        The room captured.
    frames : tuple of int
        Frame counts of the sample-building runs.
    width, height : int
        Image size, pixels.
    train_frames : int
        Frames of the training run; 0: no training run.
    device : str
        Torch device of the training.
    steps : int
        Training steps; 0: the room preset's.
    memory_limit_gib : float
        Address-space cap of each run, GiB; 0: :data:`LIMIT_SHARE` of the memory available when it starts.
    pixel_stride : int
        Samples from every ``pixel_stride``-th row and column, in every run.
    on_row : callable, optional
        Called with the result so far after each run (to write it as it grows).

    Returns
    -------
    dict
        ``capture`` (folder, room, frames, width, height, ``seconds``: to make it, or to load it
        from the cache),
        ``memory_total_gib``, ``memory_available_gib`` (before the runs) and ``rows``.
    """
    from regnf.core.preflight import available_memory_bytes
    from regnf.synthetic.capture import RoomCaptureConfig

    check_plan(frames, width, height, train_frames, steps, memory_limit_gib, pixel_stride)
    config = RoomCaptureConfig(width=width, height=height, n_views=max((*frames, train_frames)), coverage="full",
                               heldout_every=0)
    t0 = time.perf_counter()
    capture = cache.room_capture(room, config)
    result: dict = {
        "capture": {"folder": str(capture.root), "room": room, "frames": len(capture.frames), "width": capture.width,
                    "height": capture.height, "seconds": time.perf_counter() - t0},
        "memory_total_gib": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30,
        "memory_available_gib": available_memory_bytes() / 2**30,
        "rows": [],
    }
    runs = [("build_samples", n) for n in frames] + ([("train", train_frames)] if train_frames else [])
    for stage, n in tqdm(runs, desc="bench capture-scale", disable=not cache.progress):
        row = run_child(Path(capture.root), stage, n, device, steps, memory_limit_gib, pixel_stride)
        row.update(width=capture.width, height=capture.height, pixels=row["frames"] * capture.width * capture.height)
        result["rows"].append(row)
        if on_row is not None:
            on_row(result)
    return result


def markdown_table(result: dict) -> str:
    """One line per run: frames, pixels, seconds, peak and starting memory, the memory check's
    estimate, and a refusal's or failure's line."""
    cap = result["capture"]
    head = (f"Capture: {cap['room']}, {cap['frames']} frames of {cap['width']} x {cap['height']} "
            f"(made or loaded in {cap['seconds']:.0f} s); "
            f"memory {result['memory_total_gib']:.1f} GiB, {result['memory_available_gib']:.1f} GiB available.\n\n"
            "| run | frames | pixel stride | pixels (M) | status | seconds | peak RSS (GiB) | RSS before (GiB) "
            "| estimate (GiB) | note |\n|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in result["rows"]:
        if r["status"] in ("refused", "out_of_memory"):
            note = r["message"] + ("" if r.get("suggested_stride") is None else
                                   f" (the check accepts pixel stride {r['suggested_stride']})")
        elif r["status"] == "failed":
            note = f"exit status {r['exit_status']}: {r['message']}"
        else:
            note = f"{r['samples']:,} samples" if "samples" in r else f"{r['steps']} steps"
        cells = [("–" if r.get(k) is None else format(r[k], f)) for k, f in
                 (("seconds", ".1f"), ("peak_rss_gib", ".2f"), ("start_rss_gib", ".2f"), ("estimated_gib", ".2f"))]
        lines.append(f"| {r['stage']} | {r['frames']} | {r['pixel_stride']} | {r['pixels'] / 1e6:.1f} | "
                     f"{r['status']} | {' | '.join(cells)} | {note} |")
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """The child process: measure one run and print its row as one JSON line."""
    parser = argparse.ArgumentParser(prog="python -m regnf.benchmarks.capture_scale")
    parser.add_argument("capture", type=Path)
    parser.add_argument("stage", choices=STAGES)
    parser.add_argument("frames", type=int)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--steps", type=int, default=0)
    parser.add_argument("--memory-limit-gib", type=float, default=0.0)
    parser.add_argument("--pixel-stride", type=int, default=1)
    args = parser.parse_args(argv)
    if args.memory_limit_gib > 0:
        cap = int(args.memory_limit_gib * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    row = measure(args.capture, args.stage, args.frames, args.device, args.steps, args.pixel_stride)
    print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
