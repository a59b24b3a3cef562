"""Swap registered instances for library fields: frames, removal regions, the composite.

Frames (docs/design.md section 2), all 4x4 similarities acting on column vectors:

- ``S``: scene field frame -> scene metres (the scene field's ``to_world``);
- ``L``: library field frame -> canonical object metres (the library field's ``to_world``;
  canonical frame: +Z up, +X forward, base centred on the origin at z = 0);
- ``O``: canonical object metres -> scene metres (the instance's ``object_to_scene``).

A library field therefore enters the scene field frame through ``inv(S) @ O @ L``. An
instance that was swapped for another object of its class keeps ``O``: the new object stands
where the old one stood (base on the floor, heading kept) at its own metric size. A shown
object may also stand elsewhere than the original (``regnf generate``'s placement jitter):
the original is then removed where it was (``SubstitutedInstance.removal_to_scene``).

Removal: the ORIGINAL object (the one registered) is cut out of the scene, as its field
bounds mapped into the scene field frame (an oriented box, grown by ``box_pad``) plus the
registration's proposal box when there is one, or as a shell around its surface. Nothing
below the object's base plus ``floor_margin`` is removed: the base is the image of the
canonical z = 0 plane, the floor the object stands on. (The lowest face of the mapped box is
not used: field bounds are padded below the base, so that face lies under the floor and a cut
there would hole it.) The floor cut is a horizontal plane of the scene field frame, so the
scene field frame must have +Z up: ``S`` may rotate about Z only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.fields.similarity import decompose_similarity

from .composite_field import CompositeConfig, CompositeField
from .placement import PlacedObject
from .regions import OrientedBoxRegion, RemovalRegion, ShellRegion
from .stage_config import DEFAULT_STAGE_COMPOSITE, StageCompositeConfig

Z_UP_TOL = 1e-6
"""Largest deviation of the scene field's z axis from world +Z accepted by the floor cut."""

TINTS: tuple[tuple[float, float, float], ...] = (
    (1.0, 0.55, 0.55),
    (0.55, 1.0, 0.55),
    (0.55, 0.65, 1.0),
    (1.0, 0.95, 0.45),
    (1.0, 0.6, 1.0),
    (0.5, 1.0, 1.0),
)
"""Per-instance tints (multiplied into the library colour), cycled by instance id."""


class SubstitutedInstance(NamedTuple):
    """One instance to swap: what is removed and what is shown."""

    instance_id: int
    """>= 1, the id renders report for this instance."""
    shown: Field
    """The library field placed (the instance's current selection), in its own frame."""
    original: Field
    """The library field that was registered (its box or shell is removed)."""
    object_to_scene: np.ndarray
    """(4, 4) float64 canonical object metres -> scene metres."""
    proposal: OrientedBox | None = None
    """The registration's proposal box in the SCENE FIELD frame, or None."""
    name: str = ""
    """Instance name, for error messages."""
    removal_to_scene: np.ndarray | None = None
    """(4, 4) float64 canonical object metres -> scene metres of the ORIGINAL object, where it is
    removed, when the shown object stands elsewhere (a placement jitter moved it); None: at
    ``object_to_scene``."""

    @property
    def removed_at(self) -> np.ndarray:
        """(4, 4) where the original object is removed: ``removal_to_scene`` or ``object_to_scene``."""
        return self.object_to_scene if self.removal_to_scene is None else self.removal_to_scene


def as_matrix(M: object, what: str) -> np.ndarray:
    """``M`` as a (4, 4) float64 similarity, or ``ValueError`` naming ``what``."""
    A = np.asarray(M.detach().cpu() if hasattr(M, "detach") else M, dtype=np.float64)
    try:
        decompose_similarity(A)
    except ValueError as exc:
        raise RegnfError(f"{what} is not a similarity: {exc}") from exc
    return A


def library_to_scene(
    scene_to_world: np.ndarray, object_to_scene: np.ndarray, library_to_world: np.ndarray
) -> np.ndarray:
    """(4, 4) float64 library FIELD frame -> scene FIELD frame: ``inv(S) @ O @ L``.

    Parameters
    ----------
    scene_to_world : (4, 4) float
        ``S``, scene field frame -> scene metres.
    object_to_scene : (4, 4) float
        ``O``, canonical object metres -> scene metres.
    library_to_world : (4, 4) float
        ``L``, library field frame -> canonical object metres.
    """
    S = as_matrix(scene_to_world, "the scene's to_world")
    O = as_matrix(object_to_scene, "object_to_scene")
    L = as_matrix(library_to_world, "the library field's to_world")
    return np.linalg.solve(S, O @ L)


def check_z_up(scene_to_world: np.ndarray, what: str = "the scene field") -> None:
    """Raise ``ValueError`` unless ``S`` maps the field's +Z onto world +Z (yaw-only rotation)."""
    R, _, _ = decompose_similarity(as_matrix(scene_to_world, f"{what}'s to_world"))
    z = np.asarray(R)[:, 2]
    err = float(np.abs(z - np.array([0.0, 0.0, 1.0])).max())
    if err > Z_UP_TOL:
        raise RegnfError(
            f"{what}'s to_world rotates its z axis to {np.round(z, 6).tolist()} in the world, not "
            f"+Z (off by {err:.3g}): the floor cut of the removal needs a field frame with +Z up "
            "(a rotation about Z only)"
        )


def base_height(scene_to_world: np.ndarray, object_to_scene: np.ndarray) -> float:
    """Scene-FIELD-frame z of an instance's base: the image of the canonical origin."""
    base = as_matrix(object_to_scene, "object_to_scene") @ np.array([0.0, 0.0, 0.0, 1.0])
    return float(np.linalg.solve(as_matrix(scene_to_world, "the scene's to_world"), base)[2])


def removal_box(
    bounds: np.ndarray, lib_to_scene: np.ndarray, box_pad: float
) -> OrientedBox:
    """The library bounds (2, 3) mapped by ``lib_to_scene`` (4, 4), half extents times ``1 + box_pad``."""
    box = OrientedBox.from_bounds(torch.as_tensor(np.asarray(bounds, dtype=np.float64)), lib_to_scene)
    return box.inflated(box_pad)


def removal_regions(
    scene: Field, inst: SubstitutedInstance, config: StageCompositeConfig
) -> list[RemovalRegion]:
    """The regions cut out of ``scene`` for ``inst`` (scene field frame, floor spared)."""
    S = scene.to_world.detach().cpu().double().numpy()
    ws = scene.world_scale
    M_orig = library_to_scene(S, inst.removed_at, inst.original.to_world)
    floor = base_height(S, inst.removed_at)
    margin = config.floor_margin / ws
    if config.removal == "shell":
        return [
            ShellRegion(
                inst.original,
                M_orig,
                config.shell_dilation / ws,
                keep_floor=floor,
                floor_margin=margin,
                cull_pad=config.cull_pad,
            )
        ]
    boxes = [removal_box(inst.original.bounds.detach().cpu().numpy(), M_orig, config.box_pad)]
    if config.use_proposal and inst.proposal is not None:
        boxes.append(inst.proposal.inflated(config.box_pad))
    return [
        OrientedBoxRegion(b.center, b.half_extents, b.rotation, keep_floor=floor, floor_margin=margin)
        for b in boxes
    ]


def build_composite(
    scene: Field,
    instances: Sequence[SubstitutedInstance],
    config: StageCompositeConfig = DEFAULT_STAGE_COMPOSITE,
) -> CompositeField:
    """The composite of ``scene`` with every instance substituted (or none in ``scene`` mode).

    Parameters
    ----------
    scene : Field
        The scene field; the composite lives in its frame and on its device.
    instances : sequence of SubstitutedInstance
        Fields on the scene's device; ignored in ``scene`` mode.
    config : StageCompositeConfig

    Raises
    ------
    ValueError
        The scene field frame is not +Z up (``substitute`` mode), an instance's matrices are
        not similarities, or ids clash (the message names the instance).
    """
    ccfg = CompositeConfig(cull_pad=config.cull_pad)
    if config.mode == "scene":
        return CompositeField(scene, config=ccfg)
    check_z_up(scene.to_world.detach().cpu().double().numpy(), f"scene field {scene.name!r}")
    S = scene.to_world.detach().cpu().double().numpy()
    objects, removals = [], []
    for inst in instances:
        try:
            M = library_to_scene(S, inst.object_to_scene, inst.shown.to_world)
            removals += removal_regions(scene, inst, config)
        except ValueError as exc:
            raise RegnfError(f"instance {inst.name or inst.instance_id!r}: {exc}") from exc
        tint = TINTS[(inst.instance_id - 1) % len(TINTS)] if config.tint else None
        objects.append(PlacedObject(inst.shown, M, inst.instance_id, tint))
    return CompositeField(scene, objects, removals, ccfg)
