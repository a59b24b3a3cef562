"""Discovery's candidates examined side by side in worker processes.

A candidate's examination (:func:`regnf.registration.discovery.examine`) is split into its
steps, each a task: the ranking of the library in the candidate's box, the full registration of
each shortlisted object, and the choice (with its refit). A step is submitted as soon as the
steps it needs have finished, so every worker stays busy until the last candidate's choice,
where whole examinations as tasks left a core idle (docs/decisions/discovery-ranking.md).

A step that fails on its input returns what the same step returns in the calling process (the
candidate skipped, or the object's failure: :mod:`regnf.registration.step_failures`), so that
one candidate does not end the others' examination.

Every step runs on one thread in its worker, as it does when discovery examines the candidates
one after another in its own process, so the result is the same bits (tested). The workers load
the fields once each from their checkpoints (:class:`~regnf.registration.discovery.FieldFiles`)
while the calling process finds the candidates, and refuse a checkpoint whose digest is not the
one its header held when discovery began.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from regnf.core.errors import RegnfError, is_regnf_error_name
from regnf.core.executors import call_pinned, local_pool
from regnf.core.threads import one_thread
from regnf.fields.field import Field
from regnf.io.checkpoint import DIGEST_KEY, load_field, read_header
from regnf.registration.candidates import Candidate
from regnf.registration.discovery import (
    Discovery,
    DiscoveryConfig,
    FieldFiles,
    Ranking,
    choose_or_skip,
    rank_or_skip,
    register_shortlisted,
)
from regnf.registration.result import RegistrationResult
from regnf.registration.sampling import SurfaceSamples, sample_surface
from regnf.registration.step_failures import StepFailed, attempt


class StepTask(NamedTuple):
    """One step of one candidate's examination, as a worker receives it (:func:`run_step`)."""

    files: FieldFiles
    digests: dict[str, str]
    """Checkpoint path -> the content digest its header held when discovery began."""
    device: str
    config: DiscoveryConfig
    step: str
    """``load`` (the fields only), ``sample`` (a library object's surface), ``rank``,
    ``register`` or ``choose``."""
    args: tuple
    """sample: (object name,); rank: (candidate, library samples); register: (ranking, object name, its samples);
    choose: (candidate, ranking, results by object name, library samples)."""


_FIELDS: dict[tuple[str, str], Field] = {}
"""The fields this worker process loaded, by (checkpoint, device): once per worker."""


def _field(path: Path, device: str, digest: str) -> Field:
    key = (str(path), device)
    if key not in _FIELDS:
        if read_header(path)[DIGEST_KEY] != digest:
            raise RegnfError(f"{path}: the checkpoint changed since discovery began")
        _FIELDS[key] = load_field(path, device=device)  # checks the file's bytes against that digest
    return _FIELDS[key]


def run_step(task: StepTask) -> Any:
    """Run one step in a worker, on the fields loaded from ``task.files``."""
    files, digests, device = task.files, task.digests, task.device
    scene = _field(files.scene, device, digests[str(files.scene)])
    library = {name: _field(p, device, digests[str(p)]) for name, p in files.library.items()}
    if task.step == "load":
        return None
    if task.step == "sample":
        name, = task.args
        with one_thread():
            return sample_surface(library[name], None, task.config.registration.library_sampling, side="library")
    if task.step == "rank":  # a Ranking, or the candidate skipped
        cand, samples = task.args
        return rank_or_skip(cand, scene, library, samples, task.config)
    if task.step == "register":  # a RegistrationResult, or a StepFailed
        ranking, name, samples = task.args
        return attempt(register_shortlisted, ranking, scene, library[name], samples, task.config)
    if task.step == "choose":
        cand, ranking, results, samples = task.args
        return choose_or_skip(cand, ranking, results, scene, library, samples, task.config)
    raise RegnfError(f"unknown discovery step {task.step!r}")


class DiscoveryWorkers:
    """A pool of worker processes that examine discovery's candidates (a context manager).

    Entering starts the workers, has each load the fields and then sample the library objects'
    surfaces (:meth:`library_samples`); :meth:`examine` examines a list of candidates; leaving
    shuts the workers down.
    """

    def __init__(self, files: FieldFiles, device: str, config: DiscoveryConfig, workers: int) -> None:
        self.files, self.device, self.config, self.workers = files, device, config, workers
        # What the workers will load must be what the caller loaded: the digests now.
        self.digests = {str(p): read_header(p)[DIGEST_KEY] for p in (files.scene, *files.library.values())}
        self._stack = contextlib.ExitStack()
        self._warming: list[cf.Future] = []
        self._sampling: dict[str, cf.Future] = {}

    def __enter__(self) -> DiscoveryWorkers:  # noqa: PYI034 (not subclassed)
        self._pool = self._stack.enter_context(local_pool(self.workers))
        try:
            self._warming = [self._submit("load", ()) for _ in range(self.workers)]
            self._sampling = {name: self._submit("sample", (name,)) for name in self.files.library}
        except BaseException:
            self._stack.close()  # __exit__ is not called when __enter__ raises
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.__exit__(*exc)

    def _submit(self, step: str, args: tuple) -> cf.Future:
        task = StepTask(self.files, self.digests, self.device, self.config, step, args)
        return self._pool.submit(call_pinned, run_step, 1, task)

    @staticmethod
    def _value(future: cf.Future, what: str) -> Any:
        """The step's value; its error raised here as one line: a ``ValueError`` for what the
        worker found wrong with the input (a ``ValueError`` or a ``RegnfError`` there), a
        ``RuntimeError`` otherwise (a bug, or a worker that died)."""
        try:
            value, error = future.result()
        except Exception as exc:  # noqa: BLE001 (the worker died: killed, out of memory)
            value, error = None, f"{type(exc).__name__}: {exc}"
        if error is not None:
            first = error.splitlines()[0] if error.strip() else "no message"
            kind = first.split(":", 1)[0]
            bad_input = kind == "ValueError" or is_regnf_error_name(kind)
            raise (ValueError if bad_input else RuntimeError)(f"discovery: {what} failed in a worker: {first}")
        return value

    def library_samples(self) -> dict[str, SurfaceSamples]:
        """Every library object's samples (``config.registration.library_sampling``), as
        :func:`~regnf.registration.discovery.discover` takes them in its own process."""
        for future in self._warming:
            self._value(future, "loading the fields")
        self._warming = []
        return {name: self._value(f, f"sampling {name}") for name, f in self._sampling.items()}

    def examine(self, cands: list[Candidate], library_samples: Mapping[str, SurfaceSamples],
                on_done: Callable[[], None]) -> list[Discovery]:
        """:func:`~regnf.registration.discovery.examine` of every candidate, in order;
        ``on_done()`` after each candidate's choice."""
        samples = dict(library_samples)
        rankings: dict[int, Ranking] = {}
        results: dict[int, dict[str, RegistrationResult | StepFailed]] = {k: {} for k in range(len(cands))}
        out: dict[int, Discovery] = {}
        pending = {self._submit("rank", (cand, samples)): ("rank", k, "") for k, cand in enumerate(cands)}
        while pending:
            done, _ = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
            for future in done:
                step, k, name = pending.pop(future)
                value = self._value(future, f"the {step} step of candidate {k}")
                if step == "rank" and isinstance(value, Discovery):  # skipped: nothing more to do
                    out[k] = value
                    on_done()
                    continue
                if step == "rank":
                    rankings[k] = value
                    for n in value.shortlisted(self.config):
                        pending[self._submit("register", (value, n, samples[n]))] = ("register", k, n)
                elif step == "register":
                    results[k][name] = value
                if step != "choose" and len(results[k]) == len(rankings[k].shortlisted(self.config)):
                    pending[self._submit("choose", (cands[k], rankings[k], results[k], samples))] = ("choose", k, "")
                elif step == "choose":
                    out[k] = value
                    on_done()
        return [out[k] for k in range(len(cands))]
