"""Object -> scene similarities as USD xform ops, and the matrix conventions between them.

regnf matrices act on column vectors (``y = M x``); ``Gf.Matrix4d`` acts on row vectors
(``y = x M``), so a regnf matrix ``M`` is stored in USD as ``M^T``. The ops written are
``xformOpOrder = [translate, orient, scale]``, which compose to ``T R S`` (column form).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from regnf.fields.similarity import decompose_similarity

OP_ORDER = ("xformOp:translate", "xformOp:orient", "xformOp:scale")
"""The ops of every instance, outermost first."""


class XformOps(NamedTuple):
    """The three op values of a similarity ``M = T(translate) R(orient) S(scale)``."""

    translate: np.ndarray
    """(3,) float64 translation."""
    orient: np.ndarray
    """(4,) float64 unit quaternion ``(w, x, y, z)`` with ``w >= 0``."""
    scale: float
    """Uniform scale, > 0."""


def ops_from_matrix(M: np.ndarray) -> XformOps:
    """Split a similarity (4, 4, column vectors) into translate / orient / scale.

    Raises
    ------
    ValueError
        If ``M`` is not a similarity (shear, non-uniform, zero or negative scale, reflection).
    """
    R, t, s = decompose_similarity(np.asarray(M, dtype=np.float64))
    x, y, z, w = Rotation.from_matrix(np.asarray(R)).as_quat()
    q = np.array([w, x, y, z])
    q = -q if q[0] < 0 else q  # one sign per rotation, so that writes are deterministic
    return XformOps(np.asarray(t, dtype=np.float64), q / np.linalg.norm(q), float(s))


def matrix_from_ops(ops: XformOps) -> np.ndarray:
    """(4, 4) float64 ``T R S`` (column vectors) of the ops."""
    M = np.eye(4)
    w, x, y, z = ops.orient
    M[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix() * float(ops.scale)  # normalised by scipy
    M[:3, 3] = ops.translate
    return M


def to_usd_matrix(M: np.ndarray) -> list[list[float]]:
    """Rows of the ``Gf.Matrix4d`` holding the column-vector matrix ``M`` (i.e. ``M^T``)."""
    return np.asarray(M, dtype=np.float64).T.tolist()


def from_usd_matrix(G: object) -> np.ndarray:
    """(4, 4) float64 column-vector matrix from a ``Gf.Matrix4d`` (or nested rows)."""
    return np.array([[float(G[i][j]) for j in range(4)] for i in range(4)]).T
