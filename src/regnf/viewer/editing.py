"""What the viewer's editing panel runs: an instance's registration refined from a pose set
by hand, a library object registered inside a box drawn in the viewer, the two sample sets of an
instance's registration, and the stage writes (``regnf view``'s Edit and New instance folders).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from regnf.core.threads import one_thread
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.pipeline import RegistrationConfig, register, sample_pair
from regnf.registration.result import registration_payload
from regnf.registration.transform import SimilarityTransform
from regnf.scene_graph import (
    SCENE_PRIM,
    ComposedScene,
    instance_path,
    provenance_from_registration,
    set_instance,
)

if TYPE_CHECKING:  # the viewer's loaded fields and composites
    from regnf.viewer.stage_viewer import Composites

HAND_METHOD = "refined from a pose set by hand in regnf view"
"""Appended to the registration method of an instance corrected in the viewer."""
NEW_BOX_PAD = 0.1
"""Without a recorded proposal box, refinement uses the library object's box at the dragged
pose grown by this fraction (the scene side is sampled inside it)."""
MIN_BOX_SIZE = 0.05
"""Smallest side of a box drawn in the panel, metres."""
DEFAULT_BOX_SIZE = (0.7, 0.7, 1.0)
"""The panel's box size, metres."""


def gone(instance_id: str) -> str:
    """The panel's message for an edit whose instance left the stage on disk."""
    return f"**{instance_id}** is no longer in the stage (changed on disk): the edit is dropped"


@dataclass
class EditState:
    """An instance being corrected in the viewer."""

    instance_id: str
    scale: float
    """The instance's scale (the gizmo moves and turns; the refinement finds the scale)."""
    gizmo: Any
    """viser's transform controls."""
    payload: dict | None = None
    """The refined registration (``regnf register --out``'s JSON), once refined."""


def instance_fields(scene: ComposedScene, composites: Composites, instance_id: str) -> tuple[Any, Any]:
    """The scene field and the library field of instance ``instance_id`` (loaded once)."""
    rec = scene.library[scene.instances[instance_id].library_name]
    return composites.field(SCENE_PRIM, scene.scene), composites.field(instance_path(instance_id), rec)


def instance_proposal(inst: Any, scene_field: Any, library_field: Any, object_to_scene: np.ndarray) -> OrientedBox:
    """The proposal box (scene field frame) of an instance: the one recorded with its
    registration, or (placed by hand) the library object's box at ``object_to_scene`` (4, 4)
    grown by :data:`NEW_BOX_PAD`."""
    reg = inst.registration
    if reg is not None and reg.proposal_center is not None and reg.proposal_half_extents is not None:
        return OrientedBox(reg.proposal_center, reg.proposal_half_extents, reg.proposal_rotation)
    S = scene_field.to_world.detach().cpu().double().numpy()
    L = library_field.to_world.detach().cpu().double().numpy()
    return OrientedBox.from_bounds(library_field.bounds, np.linalg.inv(S) @ object_to_scene @ L).inflated(NEW_BOX_PAD)


class SampleSets(NamedTuple):
    """The two point sets a registration of an instance compares, in scene metres."""

    scene: np.ndarray
    """(n, 3) float64 surface samples of the scene field inside the proposal box."""
    library: np.ndarray
    """(m, 3) float64 surface samples of the library field, placed by the instance's pose."""


def instance_samples(scene: ComposedScene, composites: Composites, instance_id: str,
                     config: RegistrationConfig | None = None) -> SampleSets:
    """The registration's two sample sets of instance ``instance_id`` at its recorded pose.

    The sampling is the registration's own (:func:`regnf.registration.pipeline.sample_pair`,
    on one thread as :func:`~regnf.registration.register` runs it: the same points for the same
    fields, box and settings); ``config`` defaults to the registration's defaults (what
    ``regnf register`` and the demo use). The library samples are placed by the stage's
    transform, so a right pose puts them on the scene samples.
    """
    inst = scene.instances[instance_id]
    scene_field, library_field = instance_fields(scene, composites, instance_id)
    S = scene_field.to_world.detach().cpu().double().numpy()
    L = library_field.to_world.detach().cpu().double().numpy()
    O = np.asarray(inst.object_to_scene, dtype=np.float64)
    proposal = instance_proposal(inst, scene_field, library_field, O)
    with one_thread():
        a, b = sample_pair(scene_field, library_field, proposal, config or RegistrationConfig())
    to_metres = O @ L
    return SampleSets(np.asarray(a.points, dtype=np.float64) @ S[:3, :3].T + S[:3, 3],
                      np.asarray(b.points, dtype=np.float64) @ to_metres[:3, :3].T + to_metres[:3, 3])


def refine_from_pose(stage: Path, scene: ComposedScene, composites: Composites, instance_id: str,
                     object_to_scene: np.ndarray) -> dict:
    """The registration of instance ``instance_id`` refined from the pose ``object_to_scene``
    (4, 4) (object -> scene metres), as ``regnf register --out`` writes it.

    The proposal box is the one recorded with the instance, or (placed by hand) the library
    object's box at ``object_to_scene`` grown by :data:`NEW_BOX_PAD`.
    """
    scene_field, library_field = instance_fields(scene, composites, instance_id)
    S = scene_field.to_world.detach().cpu().double().numpy()
    L = library_field.to_world.detach().cpu().double().numpy()
    O = np.asarray(object_to_scene, dtype=np.float64)
    # scene field -> metres -> the object's canonical metres -> library field
    start = SimilarityTransform.from_matrix(np.linalg.inv(L) @ np.linalg.inv(O) @ S)
    proposal = instance_proposal(scene.instances[instance_id], scene_field, library_field, O)
    result = register(scene_field, library_field, proposal, initial=start)
    rec = scene.library[scene.instances[instance_id].library_name]
    payload = registration_payload(result, scene_field, library_field, scene.scene.checkpoint, rec.checkpoint)
    payload["method"] = f"{result.method}, {HAND_METHOD}"
    return payload


def register_box(scene: ComposedScene, composites: Composites, library_name: str,
                 box_to_scene: np.ndarray, half_extents: np.ndarray) -> dict:
    """The registration of library object ``library_name`` inside a box drawn in the viewer, as
    ``regnf register --out`` writes it.

    Parameters
    ----------
    box_to_scene : (4, 4) float
        Rigid pose of the box (its centre and axes) in scene metres.
    half_extents : (3,) float
        Half sizes in metres.
    """
    rec = scene.library[library_name]
    scene_field = composites.field(SCENE_PRIM, scene.scene)
    library_field = composites.field(f"library object {library_name!r}", rec)
    S = scene_field.to_world.detach().cpu().double().numpy()
    box_m = OrientedBox(box_to_scene[:3, 3], half_extents, box_to_scene[:3, :3])
    result = register(scene_field, library_field, box_m.transformed(np.linalg.inv(S)))
    payload = registration_payload(result, scene_field, library_field, scene.scene.checkpoint, rec.checkpoint)
    payload["library_name"] = library_name
    payload["method"] = f"{result.method}, inside a box drawn in regnf view"
    return payload


def write_refined(stage: Path, instance_id: str, payload: dict, allow_outside: bool = False) -> None:
    """Write a refined registration (:func:`refine_from_pose`) to instance ``instance_id``:
    accepted by the user, so recorded as forced when below the acceptance threshold."""
    provenance = provenance_from_registration(payload, forced=not payload["accepted"])
    set_instance(stage, instance_id, np.asarray(payload["object_to_scene_metres"], dtype=np.float64),
                 provenance, allow_outside=allow_outside)
