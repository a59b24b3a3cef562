"""The up of a scene field for ``regnf discover`` and ``regnf register``: ``--up``, else the field's own.

A field trained by ``regnf train`` records the up of its capture's metric world in its
provenance (``up``, 3 floats); ``--up auto`` uses it, and +Z (regnf's rooms, the library's own
up) for a field that records none. Discovery's candidates stand on the up in scene metres;
the registration's upright prior takes it in the field frame (:func:`field_frame_up`).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from regnf.captures.up_axis import parse_up, up_text
from regnf.core.errors import RegnfError
from regnf.fields.field import Field
from regnf.registration.pipeline import RegistrationConfig

PLUS_Z = (0.0, 0.0, 1.0)
"""The up of a field that records none: regnf's rooms and library objects are +Z up."""


class SceneUp(NamedTuple):
    """A scene field's up and where it came from."""

    metres: np.ndarray
    """(3,) float64 unit up in scene metres."""
    line: str
    """``up: +Z (from the scene field's training)``, for the command's output."""


def scene_up(scene: Field, value: str) -> SceneUp:
    """``--up value`` for ``scene``: the named axis, or (``auto``) the field's recorded up, else +Z.

    Raises
    ------
    ValueError
        A value not in :data:`regnf.captures.up_axis.UP_CHOICES`, or a recorded up that is not
        3 finite numbers of non-zero length.
    """
    given = parse_up(value)
    if given is not None:
        return SceneUp(given, f"up: {up_text(given)} (given by --up)")
    recorded = scene.info.provenance.get("up")
    if recorded is None:
        return SceneUp(np.array(PLUS_Z), "up: +Z (the scene field records no up; regnf's default)")
    up = np.asarray(recorded, dtype=np.float64)
    if up.shape != (3,) or not np.isfinite(up).all() or not np.linalg.norm(up) > 0:
        raise RegnfError(f"the scene field's provenance 'up' must be 3 finite numbers, not all 0, got {recorded!r}")
    up = up / np.linalg.norm(up)
    return SceneUp(up, f"up: {up_text(up)} (from the scene field's training)")


def field_frame_up(scene: Field, up: np.ndarray) -> tuple[float, float, float]:
    """``up`` (scene metres) in the field frame: the field's ``to_world`` rotation undone."""
    A = scene.to_world.detach().cpu().double().numpy()[:3, :3]
    d = A.T @ np.asarray(up, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return (float(d[0]), float(d[1]), float(d[2]))


def set_apart(*ups: tuple[float, float, float]) -> bool:
    """Whether any of the nested options' ups (``--registration.scene-sampling.up``, ...) was set
    away from its default +Z: with ``--up auto`` such an option is kept as given."""
    return any(tuple(float(v) for v in up) != PLUS_Z for up in ups)


def with_scene_up(registration: RegistrationConfig, scene: Field, up: np.ndarray) -> RegistrationConfig:
    """``registration`` with its scene sampling (the upright prior) standing on ``up`` (scene metres)."""
    sampling = dataclasses.replace(registration.scene_sampling, up=field_frame_up(scene, up))
    return dataclasses.replace(registration, scene_sampling=sampling)
