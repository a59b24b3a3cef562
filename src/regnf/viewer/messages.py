"""What a browser sends the viewer, checked before use.

A viewport is clamped to the render limits (its aspect to :data:`MAX_ASPECT`, the pixels to the
viewer's settings, never above :data:`regnf.compositor.render_folder.MAX_PIXELS`); a camera with
a number that is not finite, or a name the panel does not offer, is ignored with a logged line.
An error in a panel callback or in a malformed message becomes one logged line, never a
traceback in the server's terminal.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from regnf.compositor.render_folder import MAX_PIXELS

log = logging.getLogger("regnf.viewer")

MAX_ASPECT = 5.0
"""Widest viewport rendered, width over height (its inverse: the tallest); a wider one gets an
image this wide."""
FOV_RANGE = (0.05, 3.0)
"""Vertical fields of view rendered, radians; a client's is clamped to this range."""
MAX_DISTANCE = 1.0e4
"""A camera further than this from the room's origin (metres) is ignored."""
DEFAULT_ASPECT = 4.0 / 3.0
"""Aspect of a viewport whose size is not a pair of positive numbers."""


def ignored(what: str, value: object) -> None:
    """Log one line: a client's ``what`` was not used."""
    text = " ".join(repr(value).split())
    log.warning("regnf view: ignored %s from a client: %s", what, text if len(text) <= 80 else text[:77] + "...")


def number(value: object, what: str) -> float | None:
    """``value`` (a number, not text) as a finite float, or None (logged)."""
    try:
        x = math.nan if isinstance(value, (str, bytes, bool)) else float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        x = math.nan
    if not math.isfinite(x):
        ignored(what, value)
        return None
    return x


def vector(value: object, n: int, what: str) -> np.ndarray | None:
    """``value`` as a finite (n,) float64 array, or None (logged)."""
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        v = np.full(n, np.nan)
    if v.shape != (n,) or not np.isfinite(v).all():
        ignored(what, value)
        return None
    return v


def pose(position: object, wxyz: object, what: str) -> tuple[np.ndarray, np.ndarray] | None:
    """A client's pose of ``what``: (3,) position in metres and (4,) unit quaternion (w, x, y, z);
    None (logged) if a number is not finite, it lies beyond :data:`MAX_DISTANCE` or the
    quaternion has no length."""
    p, q = vector(position, 3, f"{what}'s position"), vector(wxyz, 4, f"{what}'s orientation")
    if p is None or q is None:
        return None
    if np.abs(p).max() > MAX_DISTANCE:
        ignored(f"{what} further than {MAX_DISTANCE:g} m", position)
        return None
    largest = float(np.abs(q).max())
    if largest < 1e-6:
        ignored(f"{what}'s orientation of zero length", wxyz)
        return None
    q = q / largest  # first to about 1: a huge quaternion's length does not overflow
    return p, q / np.linalg.norm(q)


def camera(position: object, wxyz: object, fov: object) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A client's camera: :func:`pose` and its vertical field of view (radians, clamped to
    :data:`FOV_RANGE`); None (logged) if any is not usable."""
    placed, f = pose(position, wxyz, "a camera"), number(fov, "a camera's field of view")
    if placed is None or f is None:
        return None
    return placed[0], placed[1], min(max(f, FOV_RANGE[0]), FOV_RANGE[1])


def viewport_aspect(width: object, height: object) -> float:
    """Width over height of a client's viewport, within [1 / MAX_ASPECT, MAX_ASPECT]
    (:data:`DEFAULT_ASPECT` if its size is not a pair of positive numbers)."""
    w, h = number(width, "a viewport width"), number(height, "a viewport height")
    if w is None or h is None or w <= 0 or h <= 0:
        return DEFAULT_ASPECT
    return min(max(w / h, 1.0 / MAX_ASPECT), MAX_ASPECT)


def render_size(pixels: int, aspect: float) -> tuple[int, int]:
    """(width, height) of an image of about ``pixels`` (at most :data:`MAX_PIXELS`) square pixels
    whose width over height is ``aspect`` clamped to [1 / MAX_ASPECT, MAX_ASPECT]."""
    a = min(max(aspect, 1.0 / MAX_ASPECT), MAX_ASPECT) if math.isfinite(aspect) else DEFAULT_ASPECT
    p = min(max(int(pixels), 1), MAX_PIXELS)
    w = max(1, round(math.sqrt(p * a)))
    h = max(1, round(w / a))
    while w * h > MAX_PIXELS:  # rounding up both sides of a MAX_PIXELS image
        w, h = max(1, w - 1), max(1, round((w - 1) / a))
    return w, h


def known(value: object, names: Iterable[str], what: str) -> str | None:
    """``value`` if it is one of ``names``, else None (logged)."""
    if isinstance(value, str) and value in set(names):
        return value
    ignored(f"an unknown {what}", value)
    return None


def seed(value: object) -> int | None:
    """A replacement seed: an integer in [0, 2**31), else None (logged)."""
    x = number(value, "a replacement seed")
    if x is None or x != int(x) or not 0 <= x < 2**31:
        if x is not None:
            ignored("a replacement seed that is not an integer in [0, 2**31)", value)
        return None
    return int(x)


def box_size(value: object, low: float, high: float) -> np.ndarray | None:
    """A box's (3,) size in metres, each clamped to [low, high]; None (logged) if not finite."""
    v = vector(value, 3, "a box size")
    return None if v is None else np.clip(v, low, high)


def quiet(callback: Callable[..., Any], what: str, report: Callable[[str], None] | None = None) -> Callable[..., Any]:
    """``callback`` whose exception becomes one logged line (and ``report(line)``, for the panel)."""

    @functools.wraps(callback)
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return callback(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 (a client's action must not stop the viewer)
            line = f"{what} failed: {type(exc).__name__}: {' '.join(str(exc).split())}"
            log.warning("regnf view: %s", line)
            if report is not None:
                report(line)
            return None

    return run


def one_line_errors(loop: Any) -> None:
    """Report what fails in viser's event loop (a malformed message a client sent, say) as one
    logged line instead of a traceback."""

    def handler(_: Any, context: dict) -> None:
        exc = context.get("exception")
        detail = f"{type(exc).__name__}: {exc}" if exc is not None else context.get("message", "?")
        log.warning("regnf view: a client's message was not handled: %s", " ".join(str(detail).split()))

    loop.set_exception_handler(handler)


class OneLine(logging.Filter):
    """Drops the traceback of a log record, keeping its exception's message on its line
    (``websockets`` logs a failed connection handler with its traceback)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            record.msg = f"{record.getMessage()}: {type(exc).__name__}: {' '.join(str(exc).split())}"
            record.args, record.exc_info, record.exc_text = None, None, None
        return True


def one_line_logs(names: Sequence[str] = ("websockets.server",)) -> None:
    """Put :class:`OneLine` on the loggers ``names`` (once)."""
    for name in names:
        logger = logging.getLogger(name)
        if not any(isinstance(f, OneLine) for f in logger.filters):
            logger.addFilter(OneLine())
