"""A swap that changes an instance's size many times over is refused unless asked for.

A replacement keeps the instance's transform, scale included, for the object it swaps in.
When the registered object and the one swapped in are in different units (a library
distilled from millimetres beside one in metres), the new object is a thousand times too
small or too large: the original is cut out and nothing visible takes its place. The sizes
compared are the objects' bounding-box diagonals (their proxies' extents) at the instance's
scale: the world size of what stands there, and of what would.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping

import numpy as np

from regnf.core.errors import RegnfError
from regnf.registration.scale_warnings import object_scale
from regnf.scene_graph import ComposedScene, InstanceRecord

SIZE_CHANGE_LIMIT = 3.0
"""Largest ratio of the two bounding-box diagonals (the larger over the smaller) a swap may
make: the swaps within a class of the data set's library differ by at most 2x (the table and
the end table, 1.98x); a unit mix-up by 10x or more."""


class SizeChangeError(RegnfError):
    """A swap would change an instance's size by more than :data:`SIZE_CHANGE_LIMIT`."""


def diagonal(scene: ComposedScene, name: str) -> float:
    """Bounding-box diagonal of library object ``name`` in its own metres (its proxy's extent)."""
    extent = scene.library[name].proxy.extent.astype(np.float64)
    return float(np.linalg.norm(extent[1] - extent[0]))


def registered_object(scene: ComposedScene, inst: InstanceRecord) -> str:
    """The library object whose size the instance has: the one registered there (a replacement
    layer may show another already), else the one shown."""
    reg = inst.registration
    return reg.library_name if reg is not None and reg.library_name in scene.library else inst.library_name


def check_swap_sizes(scene: ComposedScene, swaps: Mapping[str, Iterable[str]], stage: str | os.PathLike,
                     limit: float = SIZE_CHANGE_LIMIT) -> None:
    """Refuse a swap that changes an instance's size by more than ``limit``.

    Parameters
    ----------
    scene : ComposedScene
        The stage as read.
    swaps : mapping of str -> iterable of str
        Instance id -> the library objects that may be swapped in for it.
    stage : str or PathLike
        The stage's file (named in the message).
    limit : float
        Largest ratio of the bounding-box diagonals, at least 1.

    Raises
    ------
    SizeChangeError
        Naming the stage, the first such instance, both objects and their sizes in metres.
    """
    for iid in sorted(swaps):  # a handful of instances
        inst = scene.instances[iid]
        s = object_scale(inst.object_to_scene)
        old = registered_object(scene, inst)
        old_m = s * diagonal(scene, old)
        for new in sorted(set(swaps[iid])):
            new_m = s * diagonal(scene, new)
            ratio = max(new_m, old_m) / max(min(new_m, old_m), 1e-300)
            if ratio > limit:
                times = f"{ratio:.0f}" if ratio >= 10 else f"{ratio:.2g}"
                raise SizeChangeError(
                    f"{stage}: instance {iid}: {new} would be {new_m:.4g} m across where {old} is {old_m:.4g} m "
                    f"(bounding-box diagonals at the instance's scale, {s:.4g}): {times}x, more than the "
                    f"{limit:g}x a swap may change; is one library in other units? (swap anyway: "
                    "allow_size_change, on the command line --allow-size-change)")
