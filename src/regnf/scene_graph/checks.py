"""The numeric rules a stage's transforms and registration records obey, in one place.

The writer (:func:`regnf.scene_graph.write_stage`, and through it every edit) and the reader
(:func:`regnf.scene_graph.read_stage`) apply the same functions, so that whatever is written can be
read back, and whatever is read can be rendered: the compositor builds each instance's
removal box from the recorded proposal box (``regnf.fields.oriented_box.OrientedBox``) and maps
each library field by ``object_to_scene``. Each check raises ``ValueError`` with a one-line
message; callers turn it into a :class:`~scene_graph.StageError` naming the file and prim.
"""

from __future__ import annotations

import math

import numpy as np

from regnf.core.errors import RegnfError
from regnf.fields.similarity import decompose_similarity

from . import layout as L
from .model import RegistrationProvenance

BOX_ROTATION_ATOL = 1e-6
"""Largest ``|R^T R - I|`` entry of a proposal box's axes. Stricter than the 1e-5 of
``regnf.fields.oriented_box.OrientedBox``, so that a box that passes here passes there too, whatever rounding either computation makes."""


def _fmt(a: np.ndarray) -> str:
    """``a`` on one line (numpy's own repr breaks matrices over several)."""
    return str(np.asarray(a, dtype=np.float64).tolist())


def check_similarity(M: np.ndarray, what: str) -> None:
    """Refuse anything but a 4x4 similarity: finite, uniform scale > 0, a proper rotation.

    Parameters
    ----------
    M : (4, 4) float
        Column-vector matrix ``[[s R, t], [0, 1]]``.
    what : str
        Its name in the message (``"object_to_scene"``).

    Raises
    ------
    ValueError
        Wrong shape, non-finite entries, a reflection or negative scale (det <= 0), shear or
        non-uniform scale, a last row other than ``[0, 0, 0, 1]``.
    """
    A = np.asarray(M, dtype=np.float64)
    if A.shape != (4, 4):
        raise RegnfError(f"{what} must be a 4x4 matrix, got shape {A.shape}")
    try:
        decompose_similarity(A)
    except ValueError as exc:
        raise RegnfError(f"{what} is not a similarity: {exc}") from exc


def check_box(center: np.ndarray, half_extents: np.ndarray, rotation: np.ndarray, what: str) -> None:
    """Refuse a proposal box the renderer cannot use.

    Parameters
    ----------
    center : (3,) float
        In the scene field frame.
    half_extents : (3,) float
        Must all be finite and > 0 (an empty or flat box removes nothing and is refused by
        the compositor).
    rotation : (3, 3) float
        Box axes as columns: orthonormal to :data:`BOX_ROTATION_ATOL` with determinant +1 (a
        reflected box is not a box the compositor accepts).
    what : str
        Its name in the message.

    Raises
    ------
    ValueError
    """
    c = np.asarray(center, dtype=np.float64)
    h = np.asarray(half_extents, dtype=np.float64)
    R = np.asarray(rotation, dtype=np.float64)
    if c.shape != (3,) or not np.isfinite(c).all():
        raise RegnfError(f"{what} center must be 3 finite numbers, got {_fmt(c)}")
    if h.shape != (3,) or not np.isfinite(h).all() or not (h > 0).all():
        raise RegnfError(f"{what} half extents must be 3 finite numbers > 0 (a box of zero size is no "
                         f"proposal), got {_fmt(h)}")
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise RegnfError(f"{what} rotation must be a finite 3x3 matrix, got {_fmt(R)}")
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > BOX_ROTATION_ATOL or det <= 0:
        raise RegnfError(f"{what} rotation must be a proper rotation (R^T R = I, det = +1), got "
                         f"|R^T R - I| = {err:.3g}, det = {det:.6g}")


def check_json_data(value: object, what: str) -> None:
    """Refuse what JSON cannot hold exactly: a mapping with string keys, lists, strings, bools,
    None and finite numbers (NaN and infinity are not JSON)."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise RegnfError(f"{what}: key {k!r} is not a string")
            check_json_data(v, f"{what}.{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            check_json_data(v, f"{what}[{i}]")
    elif isinstance(value, float) and not math.isfinite(value):
        raise RegnfError(f"{what} is {value} (not JSON)")
    elif not (value is None or isinstance(value, (str, bool, int, float))):
        raise RegnfError(f"{what} is a {type(value).__name__}, not JSON data")


def check_registration(reg: RegistrationProvenance) -> None:
    """Refuse a registration record that cannot be written, read back or rendered.

    Parameters
    ----------
    reg : RegistrationProvenance
        ``confidence`` a finite real number; ``accepted`` and ``forced`` real bools;
        ``scene_to_library`` a similarity; loss, timing and threshold keys identifiers and
        their values real numbers (NaN allowed: a loss is NaN when nothing was refined);
        the proposal box absent or complete and valid (:func:`check_box`); ``warnings`` a list
        of one-line strings.

    Raises
    ------
    ValueError
    """
    if not isinstance(reg.method, str) or not reg.method:
        raise RegnfError(f"registration 'method' must be a non-empty string, got {reg.method!r}")
    if not isinstance(reg.library_name, str):
        raise RegnfError(
            f"registration library name must be a string, got {reg.library_name!r}")
    if not is_number(reg.confidence) or not math.isfinite(reg.confidence):
        raise RegnfError(f"registration 'confidence' must be a finite number, got {reg.confidence!r}")
    for name in ("accepted", "forced"):
        if not isinstance(getattr(reg, name), (bool, np.bool_)):  # bool("false") is True: no strings
            raise RegnfError(
                f"registration '{name}' must be true or false (a boolean), got {getattr(reg, name)!r}")
    check_similarity(reg.scene_to_library, "the registration's scene_to_library")
    for label, group in (("losses", reg.losses), ("timings", reg.timings), ("thresholds", reg.thresholds)):
        bad = [k for k in group if not isinstance(k, str) or not L.KEY_RE.match(k)]
        if bad:
            raise RegnfError(f"registration {label} keys {bad} are not identifiers")
        bad = [k for k, v in group.items() if not is_number(v)]
        if bad:
            raise RegnfError(f"registration {label} {bad} are not numbers")
    if reg.discovery is not None:
        check_json_data(reg.discovery, "the registration's discovery record")
    if not isinstance(reg.warnings, list) or not all(isinstance(w, str) and w and "\n" not in w
                                                     for w in reg.warnings):
        raise RegnfError(f"registration 'warnings' must be a list of one-line strings, got {reg.warnings!r:.80}")
    box = (reg.proposal_center, reg.proposal_half_extents, reg.proposal_rotation)
    if any(b is not None for b in box):
        if any(b is None for b in box):
            raise RegnfError("the registration's proposal box needs its center, half extents and rotation")
        check_box(*box, what="the registration's proposal box")


def is_number(v: object) -> bool:
    """A real number that is not a bool (``True`` is an int to Python, and JSON ``true`` is no
    confidence)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
