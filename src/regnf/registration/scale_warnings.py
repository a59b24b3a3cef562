"""A registered scale far from 1: the library and the scene may be in different units.

Registration is scale-free (the library need not share the scene's units), so a library
distilled from meshes in millimetres is registered at a scale near 0.001 and accepted. The
result is right, but what is built on it is not: a replacement keeps the instance's scale for
the object it swaps in. Such a scale is reported as a warning (on the console, in the JSON
result, in the instance's provenance on the stage), not refused.
"""

from __future__ import annotations

import math

import numpy as np

PLAUSIBLE_SCALE = (1.0 / 3.0, 3.0)
"""Scales (library object metres -> scene metres) that need no warning: the same object's
copies differ in size by a few tens of percent, and a unit mix-up by 10x (decimetres) or more
(centimetres: 100x, millimetres: 1000x)."""

UNITS = {"millimetres": 1000.0, "centimetres": 100.0, "inches": 1000.0 / 25.4, "feet": 1000.0 / 304.8}
"""Units a size in metres may have been given in by mistake, and how many of each make a metre."""


def object_scale(object_to_scene: np.ndarray) -> float:
    """The uniform scale of a (4, 4) similarity: the cube root of its linear part's |det|."""
    return float(np.cbrt(abs(np.linalg.det(np.asarray(object_to_scene, dtype=np.float64)[:3, :3]))))


def likely_unit(ratio: float) -> str | None:
    """The unit of :data:`UNITS` whose factor is within 1.5x of ``ratio`` (>= 1), or None."""
    name, factor = min(UNITS.items(), key=lambda item: abs(math.log(ratio / item[1])))
    return name if abs(math.log(ratio / factor)) < math.log(1.5) else None


def scale_warnings(object_to_scene: np.ndarray) -> list[str]:
    """The warnings of a registered instance's scale: none inside :data:`PLAUSIBLE_SCALE`.

    Parameters
    ----------
    object_to_scene : (4, 4) array
        The library object's metres -> the scene's metres (``object_to_scene_metres``).

    Returns
    -------
    list of str
        One line, e.g. ``scale 0.0010: the library object is ~1000x its size in the scene; is
        one of them in millimetres?``, or none.
    """
    s = object_scale(object_to_scene)
    lo, hi = PLAUSIBLE_SCALE
    # The scale is recovered from a product of matrices: a bound given exactly must stay inside.
    if not math.isfinite(s) or s <= 0 or lo * (1 - 1e-9) <= s <= hi * (1 + 1e-9):
        return []
    ratio = max(s, 1.0 / s)
    times = f"{ratio:.0f}" if ratio >= 10 else f"{ratio:.1f}"
    size = f"~{times}x its size" if s < 1 else f"~1/{times} of its size"
    unit = likely_unit(ratio)
    question = f"is one of them in {unit}?" if unit else "are they in different units?"
    shown = f"{s:.4f}" if s < 10 else f"{s:.0f}"
    return [f"scale {shown}: the library object is {size} in the scene; {question}"]
