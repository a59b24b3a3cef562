"""Ground truth for registration benchmarks: the true scene -> library similarity of an
instance, its box, and the error columns of a registration against it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import trimesh

from regnf.captures.instance import Instance
from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.metrics import registration_errors, within_bars
from regnf.registration.result import RegistrationResult
from regnf.registration.transform import SimilarityTransform
from regnf.synthetic.library import make_library_object

if TYPE_CHECKING:
    from regnf.registration.discovery import Discovery, DiscoveryResult


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


def proposal_from_instance(instance: Instance, scene_to_world: np.ndarray) -> OrientedBox:
    """The instance's ground-truth oriented box, in the scene field frame (the paper's proposal)."""
    if instance.box_corners is None:
        raise RegnfError(f"instance {instance.id!r} has no box corners")
    box_m = OrientedBox.from_corners(np.asarray(instance.box_corners, dtype=np.float64))
    return box_m.transformed(np.linalg.inv(scene_to_world))


def find_instance(instances: list[Instance], library: str) -> Instance:
    """The first instance of library object ``library`` (ValueError naming what exists)."""
    for inst in instances:
        if inst.library == library:
            return inst
    raise RegnfError(f"no instance of {library!r}; the scene has {[i.library for i in instances]}")


def evaluate(result: RegistrationResult, truth: SimilarityTransform, scene: Field, library: Field,
             surface_lib: np.ndarray, diag_m: float) -> dict:
    """Metric columns of one row."""
    errs = registration_errors(
        result.transform, truth, scene_world_scale=scene.world_scale,
        library_points=surface_lib, library_diagonal_m=diag_m,
        library_to_world=library.to_world.detach().cpu().double().numpy(), symmetry=library.symmetry,
    )
    return errs._asdict()


class PairTruth(NamedTuple):
    """The ground truth of one instance, for the metrics."""

    truth: SimilarityTransform
    """True scene field frame -> library field frame."""
    proposal: OrientedBox
    """The instance's true box as a proposal (scene field frame)."""
    surface_lib: np.ndarray
    """(2000, 3) points on the library object's true surface, library field frame."""
    diagonal_m: float
    """The object's bounding-box diagonal, metres."""


def pair_truth(inst: Instance, scene: Field, library: Field, seed: int = 0) -> PairTruth:
    """Truth of capture instance ``inst`` for ``library`` registered in ``scene``."""
    S = scene.to_world.detach().cpu().double().numpy()
    L = library.to_world.detach().cpu().double().numpy()
    truth = true_scene_to_library(S, inst.object_to_world, L)
    mesh = make_library_object(inst.library).mesh
    diag = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    pts_m, _ = trimesh.sample.sample_surface(mesh, 2000, seed=seed)
    surface_lib = (np.asarray(pts_m) - L[:3, 3]) @ np.linalg.inv(L[:3, :3]).T
    return PairTruth(truth, proposal_from_instance(inst, S), surface_lib, diag)


def match_boxes(truth: list[OrientedBox], found: list[OrientedBox], min_iou: float = 0.5
                ) -> tuple[dict[int, int], list[list[float]]]:
    """Greedy one-to-one matching of found boxes to true ones by IoU (discovery's evaluation).

    Returns {true index: found index} for the pairs with IoU >= ``min_iou`` (highest IoU
    first, each box used once) and the (true, found) IoU matrix as lists.
    """
    from regnf.registration.candidates import box_iou

    iou = [[box_iou(t, f) for f in found] for t in truth]
    pairs = sorted(((iou[i][j], i, j) for i in range(len(truth)) for j in range(len(found))), reverse=True)
    matched: dict[int, int] = {}
    used: set[int] = set()
    for value, i, j in pairs:
        if value < min_iou:
            break
        if i not in matched and j not in used:
            matched[i] = j
            used.add(j)
    return matched, iou


def scored_instance(inst: Instance, discovery: Discovery | None, iou: float, candidate: int | None,
                    scene: Field, library: Mapping[str, Field]) -> dict:
    """What discovery made of one true instance, against its truth (JSON data).

    ``discovery`` is the candidate matched to it (:func:`match_boxes`), None when none was.
    Always: ``instance``, ``object``, ``iou``, ``candidate``, ``chosen``, ``confidence`` (the
    chosen object's), ``identified``, ``within_bars``; with a candidate also ``ambiguous``,
    ``right_object_screened_rank`` and ``right_object_confidence`` (its full registration, None
    if not shortlisted), or ``skipped`` (why it could not be examined); once identified, the symmetry-aware errors ``rot_geodesic_rad``,
    ``trans_m``, ``trans_rel_diag`` and ``scale_rel``.
    """
    row = {"instance": inst.id, "object": inst.library, "iou": iou, "candidate": candidate, "chosen": None,
           "confidence": None, "identified": False, "within_bars": False}
    if discovery is None:
        return row
    if discovery.skipped is not None:  # examined no object: nothing to rank
        row["skipped"] = discovery.skipped
        return row
    names = [t.library_name for t in discovery.tried]
    right = discovery.tried[names.index(inst.library)]
    row["right_object_screened_rank"] = names.index(inst.library)
    row["right_object_confidence"] = None if right.result is None else float(right.result.confidence)
    row["ambiguous"] = list(discovery.ambiguous)
    if discovery.chosen is not None:
        row["chosen"] = discovery.chosen.library_name
        row["confidence"] = float(discovery.chosen.result.confidence)
        row["identified"] = discovery.chosen.library_name == inst.library
    if row["identified"]:
        lib = library[inst.library]
        truth = pair_truth(inst, scene, lib)
        errors = evaluate(discovery.chosen.result, truth.truth, scene, lib, truth.surface_lib, truth.diagonal_m)
        sym = "_sym" if lib.symmetry.order != 1 else ""
        row.update(rot_geodesic_rad=errors[f"rot_geodesic{sym}_rad"], trans_m=errors[f"trans_m{sym}"],
                   trans_rel_diag=errors[f"trans_rel_diag{sym}"], scale_rel=errors["scale_rel"],
                   within_bars=within_bars(errors))
    return row


def score_discovery(result: DiscoveryResult, instances: list[Instance], scene: Field, library: Mapping[str, Field],
                    min_iou: float = 0.5) -> tuple[list[dict], list[dict], dict[int, int]]:
    """Every true instance scored (:func:`scored_instance`), the false instances, and the
    matching {true index: candidate index} (:func:`match_boxes`).

    A false instance is a candidate identified as a library object where no true instance is,
    or as another object than the one there: ``candidate``, ``chosen`` and ``matches`` (the
    library object of the true instance there, or None).
    """
    truth_boxes = [OrientedBox.from_corners(inst.box_corners) for inst in instances]
    matched, iou = match_boxes(truth_boxes, [d.candidate.box for d in result.discoveries], min_iou)
    rows = [scored_instance(inst, result.discoveries[matched[i]] if i in matched else None,
                            max(iou[i], default=0.0), matched.get(i), scene, library)
            for i, inst in enumerate(instances)]
    true_of = {j: i for i, j in matched.items()}
    false = [{"candidate": j, "chosen": d.chosen.library_name,
              "matches": None if j not in true_of else instances[true_of[j]].library}
             for j, d in enumerate(result.discoveries)
             if d.chosen is not None and (j not in true_of or instances[true_of[j]].library != d.chosen.library_name)]
    return rows, false, matched
