"""Which field is the scene and which the library object: told apart by the label they carry.

A field records its class in its checkpoint's header (``label``,
:class:`~regnf.fields.field.FieldInfo`): :data:`SCENE_LABEL` for a room (a field
trained on a room capture), the object's class (``chair``, ``table``) for a library object.
A room given as a library object (or an object as the scene) makes discovery sample the whole
room as one object, minutes and gigabytes before any result, so it is refused first.
"""

from __future__ import annotations

import os

from regnf.core.preflight import PreflightError
from regnf.io.checkpoint import read_header

SCENE_LABEL = "scene"
"""The label of a room's field; every other label is the class of a library object."""


def checkpoint_label(path: str | os.PathLike) -> str:
    """The label a checkpoint's header records (``object`` when it records none), read without
    its weights; raises ``CheckpointError`` (a ``ValueError``) for a file that is no checkpoint."""
    label = read_header(path).get("label", "object")
    return label if isinstance(label, str) else "object"


def check_roles(scene: tuple[str | os.PathLike, str], library: list[tuple[str | os.PathLike, str]],
                scene_option: str = "--scene", library_option: str = "--library") -> None:
    """Refuse a scene field that is not labelled :data:`SCENE_LABEL` or a library object that is.

    Parameters
    ----------
    scene : (path, label)
        The scene field's checkpoint and its label.
    library : list of (path, label)
        Each library object's checkpoint and its label.
    scene_option, library_option : str
        The options that gave them (named in the message).

    Raises
    ------
    PreflightError
        One line naming the option, the file, its label and whether the two look swapped.
    """
    rooms = [path for path, label in library if label == SCENE_LABEL]
    swapped = bool(rooms) and scene[1] != SCENE_LABEL
    hint = f"; are {scene_option} and {library_option} swapped?" if swapped else ""
    if rooms:
        raise PreflightError(f"{library_option} {rooms[0]}: is a scene field (label {SCENE_LABEL!r}), not a library "
                             f"object{hint}")
    path, label = scene
    if label != SCENE_LABEL:
        raise PreflightError(f"{scene_option} {path}: is a library object's field (label {label!r}), not a scene "
                             f"field (label {SCENE_LABEL!r}): a room's field is trained from a room capture, or "
                             f"distilled with --label {SCENE_LABEL}")
