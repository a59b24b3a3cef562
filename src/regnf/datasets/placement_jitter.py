"""Placement jitter of generated variants: each instance turned and moved on its support plane.

An instance's support plane passes through its base (the image of its canonical origin)
perpendicular to the scene's up axis, which its ``object_to_scene`` ``O`` maps the object's
+Z onto (``O[:3, 2]``, normalised). A jittered instance is turned about that axis through its
base by a yaw drawn uniformly from ``[-yaw_max, yaw_max]`` degrees and moved within the plane
by a shift drawn uniformly from the disk of radius ``shift_max`` metres: its scale and its
up axis stay, its base stays on the plane.

Draws come from a random stream of the variant's seed of its own (``default_rng([seed,
STREAM])``), so the replacements and the appearance a seed picks do not change. Instances are
visited in sorted id order; each draws :data:`TRIES` candidates up front (the stream then
does not depend on which were free) and keeps the first that collides with nothing
(:func:`collision_test`); with none free, it keeps its pose and is recorded as not moved.

Collisions are tested on points of each shown object's surface (its proxy mesh, sampled,
:func:`surface_points`): against the scene less every instance's removal region (the
original objects are removed where they were captured, wherever the shown ones stand), and
against the other instances at their decided poses (those not yet decided where they stand),
both ways: an object's points in the others' fields, theirs in its field. A point collides
more than :data:`TOLERANCE` deep; resting on the floor or touching is contact, not collision.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from regnf.core.errors import RegnfError

STREAM = 13
"""Second seed word of the placement's random stream (``default_rng([seed, STREAM])``), apart
from the appearance's (:data:`regnf.datasets.variation.STREAM`) and the capture frames'
(:data:`regnf.datasets.generate_cameras.CAPTURE_FRAMES_STREAM`)."""
TRIES = 20
"""Candidate placements drawn per instance; the first free one is kept."""
TRIES_PER_BATCH = 5
"""Candidates tested at once (a batch after the first is tested only if none before was free)."""
TOLERANCE = 0.01
"""Metres a surface point may lie inside the scene or another object without a collision."""
FLOOR_CLEARANCE = 0.02
"""Points lower than this above the base (metres) are not tested against the scene: the floor
the object rests on reads slightly inside near its base. An obstacle of the scene lower than
this is not seen."""
SURFACE_POINTS = 2000
"""Points sampled on each proxy's faces (area-weighted), besides up to :data:`VERTEX_POINTS`
of its vertices."""
VERTEX_POINTS = 500
"""Most proxy vertices (evenly chosen) added to the samples: a box's corners are its
vertices only."""

Collides = Callable[[str, np.ndarray, Mapping[str, np.ndarray]], np.ndarray]
"""``collides(instance, candidates (t, 4, 4), others)`` -> (t,) bool; ``others`` maps every
other instance to its pose (decided, or not yet moved)."""


class Jittered(NamedTuple):
    """One instance's placement in a variant."""

    object_to_scene: np.ndarray
    """(4, 4) float64 canonical object metres -> scene metres, as shown."""
    yaw_deg: float
    """Turn about the up axis through the base, degrees (0 when not moved)."""
    shift_m: tuple[float, float, float]
    """Move of the base, scene metres, perpendicular to the up axis (zeros when not moved)."""
    moved: bool
    """A free candidate was found; False: the instance keeps its pose."""


def check_ranges(yaw_deg: float, shift: float) -> None:
    """Refuse (``ValueError``) a yaw range outside 0..180 degrees or a shift outside 0..0.5 m."""
    if not (math.isfinite(yaw_deg) and 0.0 <= yaw_deg <= 180.0):
        raise RegnfError(f"jitter_yaw_deg must be between 0 and 180 degrees, got {yaw_deg}")
    if not (math.isfinite(shift) and 0.0 <= shift <= 0.5):
        raise RegnfError(f"jitter_shift must be between 0 and 0.5 metres, got {shift}")


def candidates(pose: np.ndarray, u: np.ndarray, yaw_max_deg: float,
               shift_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The placements of ``pose`` that uniform draws ``u`` (t, 3) in [0, 1) stand for.

    Returns
    -------
    poses : (t, 4, 4) float64
        ``O'``: rotation ``Rz' O[:3, :3]`` about the up axis ``z'``, base ``O[:3, 3] + shift``.
    yaw_deg : (t,) float64
    shift : (t, 3) float64
        Scene metres, perpendicular to the up axis, within ``shift_max``.
    """
    O = np.asarray(pose, dtype=np.float64)
    up = O[:3, 2] / np.linalg.norm(O[:3, 2])
    # The plane's axes: the object's forward (+X, perpendicular to its +Z) and up x forward.
    e1 = O[:3, 0] - (O[:3, 0] @ up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    yaw = yaw_max_deg * (2.0 * u[:, 0] - 1.0)
    r = shift_max * np.sqrt(u[:, 1])  # sqrt: uniform over the disk's area
    phi = 2.0 * math.pi * u[:, 2]
    shift = r[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    th = np.radians(yaw)[:, None, None]
    K = np.array([[0.0, -up[2], up[1]], [up[2], 0.0, -up[0]], [-up[1], up[0], 0.0]])
    R = np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)  # Rodrigues, (t, 3, 3)
    poses = np.broadcast_to(O, (len(u), 4, 4)).copy()
    poses[:, :3, :3] = R @ O[:3, :3]
    poses[:, :3, 3] = O[:3, 3] + shift
    return poses, yaw, shift


def draw_placements(seed: int, poses: Mapping[str, np.ndarray], yaw_max_deg: float, shift_max: float,
                    collides: Collides | None = None, tries: int = TRIES) -> dict[str, Jittered]:
    """Each instance's placement in variant ``seed`` (see the module).

    Parameters
    ----------
    seed : int
        The variant's seed.
    poses : mapping str -> (4, 4) float
        Instance id -> its ``object_to_scene`` as captured.
    yaw_max_deg, shift_max : float
        Largest turn (degrees) and move (metres); both 0: every instance keeps its pose.
    collides : callable, optional
        The collision test (:data:`Collides`, :func:`collision_test`); None: every candidate is free.
    tries : int
        Candidates per instance.

    Returns
    -------
    dict
        Instance id -> :class:`Jittered`, in sorted id order.
    """
    check_ranges(yaw_max_deg, shift_max)
    rng = np.random.default_rng([int(seed), STREAM])
    now = {iid: np.asarray(poses[iid], dtype=np.float64) for iid in sorted(poses)}
    out = {iid: Jittered(pose, 0.0, (0.0, 0.0, 0.0), False) for iid, pose in now.items()}
    if yaw_max_deg == 0.0 and shift_max == 0.0:
        return out
    for iid, pose in list(now.items()):  # a loop over instances: each sees the others' decided poses
        cand, yaw, shift = candidates(pose, rng.random((tries, 3)), yaw_max_deg, shift_max)
        others = {j: p for j, p in now.items() if j != iid}
        for first in range(0, tries, TRIES_PER_BATCH):
            batch = slice(first, first + TRIES_PER_BATCH)
            hit = np.zeros(len(cand[batch]), bool) if collides is None else np.asarray(collides(iid, cand[batch], others))
            if not hit.all():
                k = first + int(np.argmin(hit))  # the first free candidate
                out[iid] = Jittered(cand[k], float(yaw[k]), tuple(float(v) for v in shift[k]), True)
                now[iid] = cand[k]
                break
    return out


def surface_points(points: np.ndarray, faces: np.ndarray, count: int = SURFACE_POINTS,
                   vertices: int = VERTEX_POINTS) -> np.ndarray:
    """(n, 3) float64 points on a mesh (``points`` (v, 3), ``faces`` (f, 3)): ``count`` area-weighted
    samples of its faces (a fixed seed: the same points on every run) and up to ``vertices``
    of its vertices, evenly chosen."""
    P = np.asarray(points, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    keep = P[np.unique(np.linspace(0, len(P) - 1, min(len(P), vertices)).round().astype(np.int64))]
    a, b, c = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if len(F) == 0 or not area.sum() > 0:
        return keep
    rng = np.random.default_rng(0)
    f = rng.choice(len(F), size=count, p=area / area.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1.0  # fold the square onto the triangle
    u, v = np.where(flip, 1.0 - u, u), np.where(flip, 1.0 - v, v)
    return np.concatenate([keep, a[f] + u[:, None] * (b[f] - a[f]) + v[:, None] * (c[f] - a[f])])


def _apply(M: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Points ``p`` (..., n, 3) mapped by ``M`` (..., 4, 4)."""
    return p @ M[..., :3, :3].transpose(-1, -2) + M[..., None, :3, 3]


def collision_test(composite: Any, proxies: Mapping[str, Any], instance_ids: Mapping[str, int],
                   tolerance: float = TOLERANCE, clearance: float = FLOOR_CLEARANCE) -> Collides:
    """The collision test of a variant's instances in ``composite`` (see the module).

    Parameters
    ----------
    composite : CompositeField
        The variant with every instance removed where it was captured (its placed objects
        give the fields; where they stand does not matter).
    proxies : mapping str -> ProxyMesh
        Instance id -> the proxy mesh (``points``, ``faces``; canonical object metres) of the
        object it shows.
    instance_ids : mapping str -> int
        Instance id -> its id in ``composite``.
    tolerance, clearance : float
        :data:`TOLERANCE` and :data:`FLOOR_CLEARANCE`, metres.

    Returns
    -------
    callable
        :data:`Collides`. A point outside the scene field's bounds collides (nothing is known there).
    """
    dev = composite.device
    S_inv = torch.linalg.inv(composite.scene.to_world.detach().double().to(dev))
    ws = float(composite.scene.world_scale)
    lo, hi = composite.scene.bounds.detach().double().to(dev)
    fields = {iid: composite.placements[composite.instance_ids.index(int(k))].field for iid, k in instance_ids.items()}
    pts = {iid: torch.as_tensor(surface_points(p.points, p.faces), device=dev) for iid, p in proxies.items()}

    def scene_clear(q: torch.Tensor) -> torch.Tensor:
        """(m,) bool: scene metres points ``q`` (m, 3) clear of the masked scene."""
        x = _apply(S_inv, q)
        inside = ((x >= lo) & (x <= hi)).all(dim=-1)
        ok = inside.clone()
        idx = inside.nonzero().squeeze(1)
        if idx.numel():
            with torch.no_grad():
                d = composite.scene_masked(x[idx].float()).sdf.double() * ws
            ok[idx] = d > -tolerance
        return ok

    def object_clear(iid: str, poses: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """(t, m) bool: points ``q`` (t, m, 3) clear of instance ``iid`` at ``poses`` (t, 4, 4)."""
        field = fields[iid]
        L = field.to_world.detach().double().to(dev)
        to_field = torch.linalg.inv(poses @ L)  # scene metres -> library field frame, per pose
        z = _apply(to_field, q)
        scale = torch.linalg.det(poses[:, :3, :3] @ L[:3, :3]).abs() ** (1.0 / 3.0)  # metres per field unit
        b = field.bounds.detach().double().to(dev)
        near = ((z >= b[0]) & (z <= b[1])).all(dim=-1)  # outside its bounds, nothing of it
        ok = torch.ones_like(near)
        idx = near.nonzero(as_tuple=True)
        if idx[0].numel():
            with torch.no_grad():
                d = field.sdf(z[idx].float()).double() * scale[idx[0]]
            ok[idx] = d > -tolerance
        return ok

    def collides(iid: str, cand: np.ndarray, others: Mapping[str, np.ndarray]) -> np.ndarray:
        C = torch.as_tensor(np.asarray(cand, dtype=np.float64), device=dev)  # (t, 4, 4)
        t, P = len(C), pts[iid]
        q = _apply(C, P.expand(t, -1, -1))  # (t, n, 3) scene metres
        height = P[:, 2] * torch.linalg.det(C[0, :3, :3]).abs() ** (1.0 / 3.0)
        free = scene_clear(q[:, height > clearance].reshape(-1, 3)).reshape(t, -1).all(dim=1)
        for j, pose in others.items():  # a loop over the other instances
            Pj = torch.as_tensor(np.asarray(pose, dtype=np.float64), device=dev)
            free &= object_clear(j, Pj.expand(t, 4, 4), q).all(dim=1)
            free &= object_clear(iid, C, _apply(Pj, pts[j]).expand(t, -1, -1)).all(dim=1)
        return (~free).cpu().numpy()

    return collides


def moved_scene(scene: Any, placed: Mapping[str, Jittered]) -> Any:
    """``scene`` (a ComposedScene) with each instance of ``placed`` at its new pose (in memory)."""
    instances = {iid: dataclasses.replace(inst, object_to_scene=placed[iid].object_to_scene) if iid in placed else inst
                 for iid, inst in scene.instances.items()}
    return dataclasses.replace(scene, instances=instances)


def manifest_entry(placed: Mapping[str, Jittered]) -> dict[str, Any]:
    """Instance id -> ``yaw_deg``, ``shift_m`` (3,), ``moved`` and ``object_to_scene`` (4 x 4 rows)."""
    return {iid: {"yaw_deg": j.yaw_deg, "shift_m": list(j.shift_m), "moved": j.moved,
                  "object_to_scene": np.asarray(j.object_to_scene, dtype=np.float64).tolist()}
            for iid, j in sorted(placed.items())}


def record_in_layer(layer: Path, poses: Mapping[str, np.ndarray]) -> None:
    """Write ``poses`` (instance id -> (4, 4) object_to_scene) into the replacement layer
    ``layer`` as overrides of each instance's xform ops and ``regnf:objectToScene``, so that
    the layer composes to the placements shown. The layer is replaced atomically, under its
    folder's lock (the lock stage writers take)."""
    from pxr import Gf, Sdf, Vt

    from regnf.core.atomic_io import atomic_path
    from regnf.scene_graph import layout as L
    from regnf.scene_graph import stage_lock
    from regnf.scene_graph.xform import OP_ORDER, ops_from_matrix, to_usd_matrix

    if not poses:
        return
    T = Sdf.ValueTypeNames

    def attr(spec: Sdf.PrimSpec, name: str, type_name: Any, value: object, custom: bool,
             uniform: bool = False) -> None:
        a = spec.attributes.get(name) or Sdf.AttributeSpec(
            spec, name, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying, custom)
        a.default = value

    with stage_lock(layer):
        data = Sdf.Layer.OpenAsAnonymous(str(layer))  # not the registry's: the file as it is now
        parent = data.GetPrimAtPath(L.INSTANCES) or Sdf.PrimSpec(
            data.GetPrimAtPath(L.WORLD) or Sdf.PrimSpec(data, "World", Sdf.SpecifierOver, ""),
            "Instances", Sdf.SpecifierOver, "")
        for iid, M in sorted(poses.items()):  # a loop over instances
            spec = data.GetPrimAtPath(L.instance_path(iid)) or Sdf.PrimSpec(parent, iid, Sdf.SpecifierOver, "")
            ops = ops_from_matrix(M)
            w, x, y, z = ops.orient.tolist()
            attr(spec, OP_ORDER[0], T.Double3, Gf.Vec3d(*ops.translate.tolist()), False)
            attr(spec, OP_ORDER[1], T.Quatd, Gf.Quatd(w, x, y, z), False)
            attr(spec, OP_ORDER[2], T.Double3, Gf.Vec3d(ops.scale, ops.scale, ops.scale), False)
            attr(spec, "xformOpOrder", T.TokenArray, Vt.TokenArray(list(OP_ORDER)), False, uniform=True)
            attr(spec, L.A_OBJECT_TO_SCENE, T.Matrix4d, Gf.Matrix4d(to_usd_matrix(M)), True)
        with atomic_path(layer) as tmp:
            if not data.Export(str(tmp)):
                raise OSError(f"{layer}: the placements could not be written")
