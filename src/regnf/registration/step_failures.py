"""A step of discovery that fails on its input: recorded and skipped, not the end of the run.

A real capture holds boxes that cannot be registered: a candidate whose box the scene's
sampling leaves with too few surface points, a cloud with no spread, two clouds in which
RANSAC finds no transform at all. Each is a failure of that candidate (or of one library
object in it), not of the discovery: :func:`attempt` turns it into a :class:`StepFailed`
value that the caller records. What counts as such a failure is :data:`SKIPPED_ERRORS`; any
other exception is a bug and still ends the run.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, TypeVar

import torch

SKIPPED_ERRORS: tuple[type[Exception], ...] = (ValueError, torch.linalg.LinAlgError)
"""Exceptions that fail one step on its input: the project's errors of bad input are
``ValueError`` (too few samples, a degenerate cloud, :class:`~regnf.registration.initialisation.NoHypothesisError`,
``numpy.linalg.LinAlgError``), and a singular system in torch is a ``torch.linalg.LinAlgError``."""

T = TypeVar("T")


class StepFailed(NamedTuple):
    """A step that failed on its input (:data:`SKIPPED_ERRORS`)."""

    reason: str
    """``ExceptionType: message``, the message's first line."""


def failure(exc: BaseException) -> StepFailed:
    """The :class:`StepFailed` of an exception (its type and the first line of its message)."""
    lines = str(exc).strip().splitlines()
    return StepFailed(f"{type(exc).__name__}: {lines[0] if lines else 'no message'}")


def attempt(step: Callable[..., T], *args: object) -> T | StepFailed:
    """``step(*args)``, or its failure when it raises one of :data:`SKIPPED_ERRORS`."""
    try:
        return step(*args)
    except SKIPPED_ERRORS as exc:
        return failure(exc)
