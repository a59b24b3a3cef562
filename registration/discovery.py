"""Discovery: registered instances from a scene field and a library, with no boxes given.

1. :func:`~regnf.registration.candidates.find_candidates`: upright boxes around what stands in
   the room.
2. A shortlist per candidate: library objects ranked by how well their shape's proportions
   match the candidate's box (scale-free: the library need not share the scene's units).
3. The full registration of each shortlisted object in the candidate's box; the candidate is
   the accepted object of highest confidence, or unmatched.

The same library object may be chosen for several candidates.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from regnf.neural_fields.field import Field
from regnf.neural_fields.meshing import extract_mesh
from regnf.neural_fields.oriented_box import OrientedBox
from regnf.registration.candidates import Candidate, CandidateConfig, find_candidates
from regnf.registration.pipeline import RegistrationConfig, register
from regnf.registration.result import RegistrationResult


@dataclass(frozen=True)
class DiscoveryConfig:
    """Settings of :func:`discover`."""

    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    """How candidates are found."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """How each shortlisted object is registered (its acceptance threshold decides)."""
    shortlist: int = 3
    """Library objects registered per candidate, best-matching proportions first."""
    proxy_resolution: int = 48
    """Marching-cubes cells along a library object's longest side, for its proportions."""

    def __post_init__(self) -> None:
        if self.shortlist < 1:
            raise ValueError(f"shortlist must be >= 1, got {self.shortlist}")


def proportions(half_extents: np.ndarray) -> np.ndarray:
    """(2,) scale-free shape of an upright box: log of its height over its larger horizontal
    side, and log of its smaller horizontal side over its larger one."""
    a, b = sorted((float(half_extents[0]), float(half_extents[1])), reverse=True)
    return np.log(np.array([float(half_extents[2]) / a, b / a]))


def library_proportions(library_field: Field, resolution: int = 48) -> np.ndarray:
    """:func:`proportions` of a library object standing in its canonical frame (+Z up): the
    tight box of its marching-cubes surface in canonical units."""
    mesh = extract_mesh(library_field, resolution, with_color=False, in_world=True)
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    return proportions(0.5 * (hi - lo))


class Tried(NamedTuple):
    """One library object registered in a candidate's box."""

    library_name: str
    proportion_distance: float
    """L1 distance of the log proportions (the shortlist's order)."""
    result: RegistrationResult


class Discovery(NamedTuple):
    """What became of one candidate."""

    candidate: Candidate
    """Its box and surface points, scene metres."""
    proposal: OrientedBox
    """The box in the scene field frame (what registration was given)."""
    tried: list[Tried]
    """Every shortlisted object, in the shortlist's order."""
    chosen: Tried | None
    """The accepted registration of highest confidence, or None: unmatched."""


class DiscoveryResult(NamedTuple):
    """Every candidate and what it became."""

    discoveries: list[Discovery]
    seconds: dict
    """Time of ``candidates`` and ``registration``, and the ``total``."""

    @property
    def instances(self) -> list[Discovery]:
        """The candidates that were identified."""
        return [d for d in self.discoveries if d.chosen is not None]

    @property
    def unmatched(self) -> list[Discovery]:
        return [d for d in self.discoveries if d.chosen is None]


def discover(scene_field: Field, library: Mapping[str, Field],
             config: DiscoveryConfig | None = None) -> DiscoveryResult:
    """Find, identify and register the library's objects in a scene field, with no boxes.

    Parameters
    ----------
    scene_field : Field
        A room (``to_world`` to metres, +Z up by default).
    library : mapping of name -> Field
        Library objects standing upright in their canonical frames; on the scene's device.
    config : DiscoveryConfig

    Returns
    -------
    DiscoveryResult
        One :class:`Discovery` per candidate, largest first.
    """
    cfg = config or DiscoveryConfig()
    if not library:
        raise ValueError("discovery needs at least one library object")
    t0 = time.perf_counter()
    found = find_candidates(scene_field, cfg.candidates)
    t1 = time.perf_counter()
    shapes = {name: library_proportions(f, cfg.proxy_resolution) for name, f in library.items()}
    S_inv = np.linalg.inv(scene_field.to_world.detach().cpu().double().numpy())
    discoveries = []
    for cand in found.candidates:  # one iteration per candidate (a handful per room)
        own = proportions(cand.box.half_extents)
        ranked = sorted(shapes, key=lambda n: (float(np.abs(shapes[n] - own).sum()), n))
        proposal = cand.box.transformed(S_inv)
        tried = [Tried(name, float(np.abs(shapes[name] - own).sum()),
                       register(scene_field, library[name], proposal, cfg.registration))
                 for name in ranked[:cfg.shortlist]]
        accepted = [t for t in tried if t.result.accepted]
        chosen = max(accepted, key=lambda t: t.result.confidence) if accepted else None
        discoveries.append(Discovery(cand, proposal, tried, chosen))
    t2 = time.perf_counter()
    return DiscoveryResult(discoveries, {"candidates": t1 - t0, "registration": t2 - t1, "total": t2 - t0})
