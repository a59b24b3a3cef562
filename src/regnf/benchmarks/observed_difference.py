"""How much of what tells two library objects apart a scene field's views observed.

A wrong library object in another object's box can only lose to the right one on evidence the
scene holds. Where the two shapes differ only in a part the capture never saw (a pillow on the
far side of a chair, say), no registration can rank them, and the benchmark says so: it places
both meshes at the box object's true pose, takes the surface of each that lies more than a
tolerance from the other (their symmetric difference), and reads the scene field's visibility
grid there (:meth:`regnf.observations.visibility.VisibilityGrid.observed`).
"""

from __future__ import annotations

import numpy as np
import trimesh

from regnf.fields.field import Field
from regnf.registration.observed_difference import DIFFERENCE_TOLERANCE, observed_share
from regnf.synthetic.primitives import surface_distance

SAMPLES = 4000
"""Surface samples per shape."""


def observed_difference(scene: Field, object_to_world: np.ndarray, mesh_a: trimesh.Trimesh,
                        mesh_b: trimesh.Trimesh, seed: int = 0) -> float:
    """Mean observation weight of the surface where two shapes differ, both at one pose.

    Parameters
    ----------
    scene : Field
        The scene field; its ``visibility`` grid (None: everything observed, the result is 1).
    object_to_world : (4, 4) float
        The pose of both shapes (the box object's true pose), object frame -> world, metres.
    mesh_a, mesh_b : trimesh.Trimesh
        The two library objects in their object frames, metres.
    seed : int
        Surface sampling seed.

    Returns
    -------
    float
        :func:`regnf.registration.observed_difference.observed_share` of the differing surface:
        0 when no view observed any of it, 1 when every part was fully observed.
    """
    diag = float(np.linalg.norm(mesh_b.extents))
    parts = []
    for mesh, other, s in ((mesh_a, mesh_b, seed), (mesh_b, mesh_a, seed + 1)):
        pts, _ = trimesh.sample.sample_surface(mesh, SAMPLES, seed=s)
        parts.append(pts[surface_distance(other, pts) > DIFFERENCE_TOLERANCE * diag])
    M = np.asarray(object_to_world, dtype=np.float64)
    world_to_field = np.linalg.inv(scene.to_world.detach().cpu().double().numpy())
    x = np.concatenate(parts) @ M[:3, :3].T + M[:3, 3]
    return observed_share(scene, x @ world_to_field[:3, :3].T + world_to_field[:3, 3])
