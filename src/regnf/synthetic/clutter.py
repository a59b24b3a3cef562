"""Small clutter objects (boxes, cans, a bowl) resting on a table top."""

from __future__ import annotations

import numpy as np
import trimesh

from regnf.captures.instance import yaw_pose
from regnf.synthetic.placement import place_circles
from regnf.synthetic.primitives import Part, box, canonicalise, cylinder, union_parts

CLUTTER_COLORS: tuple[tuple[float, float, float], ...] = (
    (0.78, 0.20, 0.15),
    (0.20, 0.36, 0.72),
    (0.92, 0.76, 0.18),
    (0.24, 0.56, 0.30),
    (0.93, 0.92, 0.88),
)
"""Clutter albedos: saturated, unlike the furniture woods and fabrics."""


def _bowl(color: tuple[float, float, float]) -> trimesh.Trimesh:
    """A spherical bowl with a flat base, walls about 2 cm thick, base at z = 0."""
    r = 0.09
    outer = trimesh.creation.icosphere(subdivisions=3, radius=r)
    # Keep the lower part of the outer sphere, flat-bottomed.
    lower = trimesh.creation.box(extents=(3 * r, 3 * r, 0.75 * r))
    lower.apply_translation([0.0, 0.0, -0.375 * r])
    shell = trimesh.boolean.intersection([outer, lower], engine="manifold")
    # A raised inner sphere hollows it out and leaves a thick base.
    inner = trimesh.creation.icosphere(subdivisions=3, radius=0.075)
    inner.apply_translation([0.0, 0.0, 0.03])
    bowl = trimesh.boolean.difference([shell, inner], engine="manifold")
    bowl.visual.face_colors = np.r_[np.round(np.asarray(color) * 255), 255].astype(np.uint8)
    return canonicalise(bowl)


def _clutter_item(kind: int, rng: np.random.Generator, color: tuple) -> trimesh.Trimesh:
    """One clutter item standing on z = 0, centred on the z axis."""
    if kind == 0:
        size = rng.uniform([0.08, 0.08, 0.06], [0.22, 0.16, 0.18])
        parts: list[Part] = [box(size, (0.0, 0.0, size[2] / 2), color, "box")]
    elif kind == 1:
        radius, height = rng.uniform(0.035, 0.06), rng.uniform(0.09, 0.2)
        parts = [cylinder(radius, 0.0, height, (0.0, 0.0), color, "can")]
    else:
        return _bowl(color)
    return canonicalise(union_parts(parts, context="clutter"))


def make_table_clutter(
    top_half_extent: tuple[float, float],
    top_z: float,
    rng: np.random.Generator,
    count: int | None = None,
) -> list[trimesh.Trimesh]:
    """3-5 clutter meshes resting on a table top, in the table's canonical frame.

    Parameters
    ----------
    top_half_extent : (2,) float
        Half sizes of the (rectangular) table top along x and y, metres.
    top_z : float
        Height of the table top.
    count : int, optional
        Number of items; random in [3, 5] if None.

    Returns
    -------
    list of trimesh.Trimesh
        Coloured, closed meshes in the table's canonical frame.
    """
    n = int(rng.integers(3, 6)) if count is None else count
    items = [_clutter_item(k % 3, rng, CLUTTER_COLORS[k % len(CLUTTER_COLORS)]) for k in range(n)]
    radii = np.array([np.linalg.norm(m.vertices[:, :2], axis=1).max() for m in items])
    centres = place_circles(
        radii, top_half_extent, gap=0.04, margin=0.05, rng=rng, context="table clutter"
    )
    for mesh, c in zip(items, centres):
        mesh.apply_transform(yaw_pose(rng.uniform(0.0, 2 * np.pi), np.array([c[0], c[1], top_z])))
    return items
