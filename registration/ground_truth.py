"""Ground truth for registration benchmarks: the true scene -> library similarity of an instance."""

from __future__ import annotations

import numpy as np

from regnf.registration.proposal import ProposalBox
from regnf.registration.transform import SimilarityTransform
from regnf.synthetic.instance import Instance


def true_scene_to_library(
    scene_to_world: np.ndarray, object_to_world: np.ndarray, library_to_world: np.ndarray
) -> SimilarityTransform:
    """T_gt = L^-1 ∘ O^-1 ∘ S: scene field -> room metres -> canonical object -> library field.

    Parameters
    ----------
    scene_to_world : (4, 4) float   scene field frame -> room metres
    object_to_world : (4, 4) float  canonical object metres -> room metres (the instance pose)
    library_to_world : (4, 4) float library field frame -> canonical object metres
    """
    M = np.linalg.inv(library_to_world) @ np.linalg.inv(object_to_world) @ scene_to_world
    return SimilarityTransform.from_matrix(M)


def proposal_from_instance(instance: Instance, scene_to_world: np.ndarray) -> ProposalBox:
    """The instance's ground-truth oriented box, in the scene field frame (the paper's proposal)."""
    if instance.box_corners is None:
        raise ValueError(f"instance {instance.id!r} has no box corners")
    box_m = ProposalBox.from_corners(np.asarray(instance.box_corners, dtype=np.float64))
    return box_m.transformed(np.linalg.inv(scene_to_world))


def find_instance(instances: list[Instance], library: str) -> Instance:
    """The first instance of library object ``library`` (ValueError naming what exists)."""
    for inst in instances:
        if inst.library == library:
            return inst
    raise ValueError(f"no instance of {library!r}; the scene has {[i.library for i in instances]}")
