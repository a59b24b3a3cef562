"""What a registration returns: the similarity, how sure we are, and how we got there."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field

import numpy as np

from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.scale_warnings import scale_warnings
from regnf.registration.transform import SimilarityTransform


@dataclass
class HypothesisReport:
    """One initial hypothesis and what refining it gave."""

    initial: SimilarityTransform
    """Scene -> library transform from the initialisation."""
    refined: SimilarityTransform
    """Scene -> library transform after refinement (== initial when not refined)."""
    init_fitness: float
    """Fraction of inlier correspondences after ICP."""
    loss: float
    """Final refinement loss (nan when not refined)."""
    confidence: float
    """Inlier fraction of the SDF residuals after refinement times the library object's fraction in the proposal."""

    def to_json(self) -> dict:
        return {
            "initial": self.initial.to_json(),
            "refined": self.refined.to_json(),
            "init_fitness": float(self.init_fitness),
            "loss": float(self.loss),
            "confidence": float(self.confidence),
        }


@dataclass
class RegistrationResult:
    """The 7-DoF similarity of a library object in a scene, with provenance."""

    transform: SimilarityTransform
    """Scene field frame -> library field frame, ``y = s R x + t``."""
    confidence: float
    """Inlier fraction of the SDF residuals (both ways) times the library object's fraction in the proposal."""
    accepted: bool
    """``confidence >= acceptance_threshold``: trust the result or report a failure."""
    method: str
    """Which method produced it (``regnf``, ``regnf-single``, ``regnf-init``, ``fgr``, ``nerf2nerf``)."""
    losses: dict = field(default_factory=dict)
    """Final loss and mean residuals of the chosen hypothesis."""
    timings: dict = field(default_factory=dict)
    """Seconds per stage: sampling, initialisation, refinement, total."""
    hypotheses: list[HypothesisReport] = field(default_factory=list)
    """Every hypothesis tried, best first."""
    proposal: OrientedBox | None = None
    """The proposal box in the scene field frame."""
    thresholds: dict = field(default_factory=dict)
    """``inlier_threshold`` and ``acceptance_threshold`` used."""
    history: list[dict] = field(default_factory=list)
    """Per-iteration refinement record of the chosen hypothesis (loss, residuals, alpha, c, s)."""
    samples: tuple[np.ndarray, np.ndarray] | None = None
    """Scene samples (scene field frame) and library samples (library field frame); not saved."""

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 scene -> library."""
        return self.transform.matrix()

    def to_json(self) -> dict:
        box = None
        if self.proposal is not None:
            box = {k: np.asarray(v).tolist() for k, v in self.proposal._asdict().items()}
        return {
            "method": self.method,
            "transform_scene_to_library": self.transform.to_json(),
            "confidence": float(self.confidence),
            "accepted": bool(self.accepted),
            "losses": {k: float(v) for k, v in self.losses.items()},
            "timings": {k: float(v) for k, v in self.timings.items()},
            "thresholds": dict(self.thresholds),
            "proposal_box": box,
            "hypotheses": [h.to_json() for h in self.hypotheses],
            "history": self.history,
        }


def asdict_plain(obj: object) -> dict:
    """``dataclasses.asdict`` with numpy arrays turned into lists (for JSON)."""
    def plain(x: object) -> object:
        if isinstance(x, np.ndarray):
            return x.tolist()
        if isinstance(x, dict):
            return {k: plain(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        return x

    return plain(asdict(obj))  # type: ignore[return-value]


def registration_payload(result: RegistrationResult, scene: Field, library: Field, scene_path: str | os.PathLike,
                         library_path: str | os.PathLike) -> dict:
    """What ``regnf register --out`` writes (and a stage records): the result, the fields, the
    object -> scene transform in metres and its ``warnings`` (a scale that suggests other units,
    :func:`~regnf.registration.scale_warnings.scale_warnings`)."""
    S = scene.to_world.detach().cpu().double().numpy()
    L = library.to_world.detach().cpu().double().numpy()
    object_to_scene = S @ result.transform.inverse().matrix() @ np.linalg.inv(L)
    return {
        **result.to_json(),
        "scene_field": str(scene_path),
        "library_field": str(library_path),
        "library_name": library.name,
        "library_label": library.label,
        "object_to_scene_metres": object_to_scene.tolist(),
        "warnings": scale_warnings(object_to_scene),
    }
