"""Registration errors against ground truth (docs/design.md section 1.7).

Both the estimate ``T`` and the truth ``T_gt`` map the SCENE field frame to the LIBRARY field
frame. Three kinds of numbers come out:

- the paper's, for comparison with its tables: translation RMSE over the three components
  of ``t - t_gt`` (library field units), RMSE of the xyz Euler-angle differences (wrapped to
  [-pi, pi]) and ``|s - s_gt|``;
- honest ones: the geodesic rotation error, the error of where the estimate puts the
  object's centre IN THE SCENE (metres and fraction of the object's diagonal), the relative
  scale error and ADD (mean displacement of the object's surface points, scene side);
- each of these also minimised over the object's declared symmetry (``*_sym``): an estimate
  ``S_theta o T`` with ``S_theta`` a rotation about the canonical +Z axis (expressed in the
  library field frame) is as good as ``T``. Each ``_sym`` number is minimised on its own.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import NamedTuple

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from regnf.core.errors import RegnfError
from regnf.fields.field import Symmetry
from regnf.fields.similarity import decompose_similarity

from .transform import SimilarityTransform

CONTINUOUS_SAMPLES = 720
"""Angles tried for a continuous symmetry before the local (bounded Brent) refinement."""

ANGLE_CHUNK = 32
"""Symmetry angles evaluated together."""


class RegistrationErrors(NamedTuple):
    """Errors of one registration estimate (see the module docstring)."""

    trans_rmse_norm: float
    """Paper: sqrt(mean((t - t_gt)^2)) over x, y, z, in library field units."""
    rot_euler_rmse_rad: float
    """Paper: RMSE of the wrapped xyz (extrinsic) Euler-angle differences, radians."""
    scale_abs: float
    """Paper: |s - s_gt|."""
    rot_geodesic_rad: float
    """Angle of R_gt^T R, radians in [0, pi]."""
    trans_m: float
    """|T^-1(c) - T_gt^-1(c)| in metres, c = the object's bbox centre (library frame)."""
    trans_rel_diag: float
    """``trans_m`` / the object's bbox diagonal in metres."""
    scale_rel: float
    """|s / s_gt - 1|."""
    add_m: float
    """Mean |T^-1(p) - T_gt^-1(p)| over the library surface points p, metres."""
    add_rel: float
    """``add_m`` / the object's bbox diagonal in metres."""
    trans_rmse_norm_sym: float
    """``trans_rmse_norm`` minimised over the symmetry group."""
    rot_euler_rmse_sym_rad: float
    """``rot_euler_rmse_rad`` minimised over the symmetry group."""
    rot_geodesic_sym_rad: float
    """``rot_geodesic_rad`` minimised over the symmetry group."""
    trans_m_sym: float
    """``trans_m`` minimised over the symmetry group."""
    trans_rel_diag_sym: float
    """``trans_rel_diag`` minimised over the symmetry group."""
    add_m_sym: float
    """``add_m`` minimised over the symmetry group."""
    add_rel_sym: float
    """``add_rel`` minimised over the symmetry group."""


def geodesic_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in [0, pi] of ``R`` (..., 3, 3), accurate near 0 and pi.

    ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)``: the same as ``arccos((tr R - 1) / 2)``
    without its loss of precision at small angles.
    """
    R = np.asarray(R, dtype=np.float64)
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    sin = 0.5 * np.linalg.norm(w, axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin, cos)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


def euler_rmse(R: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """RMSE of the wrapped differences of the xyz Euler angles of ``R`` and ``R_gt``.

    Parameters
    ----------
    R : (..., 3, 3) float
        Estimated rotations.
    R_gt : (3, 3) float

    Returns
    -------
    (...) float, radians.
    """
    R = np.asarray(R, dtype=np.float64)
    e = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("xyz").reshape(*R.shape[:-2], 3)
    e_gt = Rotation.from_matrix(np.asarray(R_gt, dtype=np.float64)).as_euler("xyz")
    return np.sqrt(np.mean(wrap_angle(e - e_gt) ** 2, axis=-1))


def symmetry_rotations(
    thetas: np.ndarray, library_to_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The symmetry maps ``S_theta`` in the LIBRARY FIELD frame: ``W^-1 o Rz(theta) o W``.

    Parameters
    ----------
    thetas : (m,) float
        Angles about the canonical +Z axis (through the canonical origin).
    library_to_world : (4, 4) float
        ``W``: library field frame -> canonical object frame (a similarity).

    Returns
    -------
    R : (m, 3, 3)
        Rotation parts (the scale of ``W`` cancels).
    t : (m, 3)
        Translation parts: ``S_theta(x) = R x + t``.
    """
    Rw, tw, sw = (np.asarray(a, dtype=np.float64) for a in decompose_similarity(library_to_world))
    th = np.asarray(thetas, dtype=np.float64).reshape(-1)
    Rz = Rotation.from_euler("z", th[:, None]).as_matrix().reshape(len(th), 3, 3)
    # x -> W^-1(Rz(W x)) = Rw^T Rz Rw x + Rw^T (Rz tw - tw) / sw
    R = Rw.T @ Rz @ Rw
    t = ((Rz @ tw - tw) @ Rw) / sw
    return R, t


def symmetry_axis(library_to_world: np.ndarray) -> np.ndarray:
    """(3,) unit vector: the canonical +Z axis (the symmetry axis) in the LIBRARY FIELD frame.

    ``library_to_world`` is ``W``: library field frame -> canonical object frame (a similarity).
    """
    Rw, _, _ = (np.asarray(a, dtype=np.float64) for a in decompose_similarity(library_to_world))
    return Rw.T @ np.array([0.0, 0.0, 1.0])


class ObjectSymmetry(NamedTuple):
    """The library object's declared symmetry, in the library field frame."""

    order: int
    """1: none; k > 1: k-fold; 0: continuous (``regnf.fields.field.Symmetry.order``)."""
    axis: np.ndarray
    """(3,) unit axis in the library field frame (``metrics.symmetry_axis`` of its to_world)."""


def same_pose(R1: np.ndarray, R2: np.ndarray, s1: float, s2: float, shift: float,
              symmetry: ObjectSymmetry | None, max_angle: float, max_scale: float,
              max_shift: float) -> bool:
    """Whether two scene -> library poses are one within tolerances.

    Parameters
    ----------
    R1, R2 : (3, 3) float
        Their rotations.
    s1, s2 : float
        Their scales.
    shift : float
        How far apart they put one point (the caller's choice of point and unit).
    symmetry : ObjectSymmetry or None
        Rotations a symmetry maps onto each other are one (None: no symmetry).
    max_angle, max_scale, max_shift : float
        The rotations are less than ``max_angle`` radians apart (modulo the symmetry), the
        scales less than the fraction ``max_scale`` and ``shift`` is below ``max_shift``.
    """
    if shift >= max_shift or abs(math.log(s1 / s2)) >= math.log1p(max_scale):
        return False
    order, axis = (1, np.array([0.0, 0.0, 1.0])) if symmetry is None else symmetry
    return symmetric_angle(np.asarray(R1) @ np.asarray(R2).T, axis, order) < max_angle


def symmetric_angle(Q: np.ndarray, axis: np.ndarray, order: int) -> float:
    """Geodesic angle from the rotation ``Q`` to the nearest symmetry rotation about ``axis``.

    Two scene -> library rotations ``R1``, ``R2`` describe the same pose of an object with
    this symmetry when ``Q = R2 R1^T`` is one of its symmetries; this is how far it is from
    being one (0 when it is).

    Parameters
    ----------
    Q : (3, 3) float
        A rotation in the library field frame.
    axis : (3,) float
        Unit symmetry axis in the library field frame (:func:`symmetry_axis`).
    order : int
        1: no symmetry (the plain geodesic angle); k > 1: rotations by 2 pi j / k;
        0: every rotation about ``axis``.
    """
    Q = np.asarray(Q, dtype=np.float64)
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    if order == 1:
        return float(geodesic_angle(Q))
    if order > 1:
        th = 2.0 * math.pi * np.arange(order) / order
        S = Rotation.from_rotvec(np.outer(th, a)).as_matrix()
        return float(geodesic_angle(np.swapaxes(S, -1, -2) @ Q).min())
    # Continuous: trace(Rot(a, th)^T Q) = a.Qa + cos(th) (tr Q - a.Qa) + sin(th) tr([a]x^T Q),
    # largest at sqrt(p^2 + q^2) above a.Qa; the angle follows from the trace.
    aqa = float(a @ Q @ a)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    p_, q_ = float(np.trace(Q)) - aqa, float(np.trace(K.T @ Q))
    best = aqa + math.hypot(p_, q_)
    return float(np.arccos(np.clip(0.5 * (best - 1.0), -1.0, 1.0)))


def _min_over_symmetry(fn: Callable[[np.ndarray], np.ndarray], symmetry: Symmetry) -> float:
    """min over the group of ``fn(thetas) -> (m,)``, vectorised over ``thetas`` (m,)."""
    order = int(symmetry.order)
    if order < 0:
        raise RegnfError(f"symmetry order must be >= 0, got {order}")
    if order == 1:
        return float(fn(np.zeros(1))[0])
    n = order if order > 1 else CONTINUOUS_SAMPLES
    grid = 2.0 * math.pi * np.arange(n) / n
    # Chunks of angles bound the memory of ADD over many points (m x n x 3).
    vals = np.concatenate([fn(grid[i : i + ANGLE_CHUNK]) for i in range(0, n, ANGLE_CHUNK)])
    if order > 1:
        return float(vals.min())
    # Continuous: the dense scan brackets the global minimum, bounded Brent polishes it.
    k = int(np.argmin(vals))
    step = 2.0 * math.pi / CONTINUOUS_SAMPLES
    res = minimize_scalar(
        lambda a: float(fn(np.array([a]))[0]),
        bounds=(grid[k] - step, grid[k] + step),
        method="bounded",
        options={"xatol": 1e-12},
    )
    return float(min(vals[k], res.fun))


def registration_errors(
    T: SimilarityTransform,
    T_gt: SimilarityTransform,
    scene_world_scale: float,
    library_points: np.ndarray,
    library_diagonal_m: float,
    library_to_world: np.ndarray,
    symmetry: Symmetry | None = None,
    library_center: np.ndarray | None = None,
) -> RegistrationErrors:
    """All errors of the estimate ``T`` against ``T_gt`` (both scene field -> library field).

    Parameters
    ----------
    T, T_gt : SimilarityTransform
        Estimate and ground truth.
    scene_world_scale : float
        Metres per scene-field unit (``scene_field.world_scale``).
    library_points : (n, 3) float
        The library object's surface points in the LIBRARY FIELD frame (for ADD).
    library_diagonal_m : float
        The object's bounding-box diagonal in metres.
    library_to_world : (4, 4) float
        The library field's ``to_world`` (field -> canonical object frame).
    symmetry : Symmetry, optional
        The object's declared symmetry about the canonical +Z axis; none by default.
    library_center : (3,) float, optional
        The object's bbox centre in the library field frame; by default the centre of the
        AABB of ``library_points``.

    Returns
    -------
    RegistrationErrors
    """
    symmetry = symmetry or Symmetry()
    P = np.asarray(library_points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0 or not np.isfinite(P).all():
        raise RegnfError(f"library_points must be a finite non-empty (n, 3) array, got {P.shape}")
    for name, v in (
        ("scene_world_scale", scene_world_scale),
        ("library_diagonal_m", library_diagonal_m),
    ):
        if not np.isfinite(v) or v <= 0:
            raise RegnfError(f"{name} must be finite and > 0, got {v}")
    for name, tr in (("T", T), ("T_gt", T_gt)):
        if not (np.isfinite(tr.matrix()).all() and tr.s > 0):
            raise RegnfError(f"{name} must be a finite similarity with s > 0")
    c = (
        0.5 * (P.min(axis=0) + P.max(axis=0))
        if library_center is None
        else np.asarray(library_center, dtype=np.float64)
    )
    w, diag = float(scene_world_scale), float(library_diagonal_m)
    R, t, s = np.asarray(T.R), np.asarray(T.t), float(T.s)
    Rg, tg, sg = np.asarray(T_gt.R), np.asarray(T_gt.t), float(T_gt.s)
    Tinv, Tg_inv = T.inverse(), T_gt.inverse()
    c_gt, P_gt = Tg_inv.apply(c[None])[0], Tg_inv.apply(P)

    def parts(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (m, 3, 3) and translation (m, 3) of S_theta o T."""
        Rs, ts = symmetry_rotations(th, library_to_world)
        return Rs @ R, Rs @ t + ts

    def trans_rmse(th: np.ndarray) -> np.ndarray:
        return np.sqrt(np.mean((parts(th)[1] - tg) ** 2, axis=-1))

    def rot_euler(th: np.ndarray) -> np.ndarray:
        return euler_rmse(parts(th)[0], Rg)

    def rot_geo(th: np.ndarray) -> np.ndarray:
        return geodesic_angle(np.swapaxes(Rg, -1, -2) @ parts(th)[0])

    def inv_apply(th: np.ndarray, X: np.ndarray) -> np.ndarray:
        """(m, n, 3): (S_theta o T)^-1 (X) = T^-1(S_theta^-1 X), in scene units."""
        Rs, ts = symmetry_rotations(th, library_to_world)
        Y = np.einsum("mji,mnj->mni", Rs, X[None] - ts[:, None, :])  # S^-1 = Rs^T (x - ts)
        return Tinv.apply(Y.reshape(-1, 3)).reshape(Y.shape)

    def trans_metres(th: np.ndarray) -> np.ndarray:
        return np.linalg.norm(inv_apply(th, c[None])[:, 0] - c_gt, axis=-1) * w

    def add_metres(th: np.ndarray) -> np.ndarray:
        return np.linalg.norm(inv_apply(th, P) - P_gt, axis=-1).mean(axis=-1) * w

    zero = np.zeros(1)
    trans_m = float(trans_metres(zero)[0])
    add_m = float(add_metres(zero)[0])
    trans_m_sym = _min_over_symmetry(trans_metres, symmetry)
    add_m_sym = _min_over_symmetry(add_metres, symmetry)
    return RegistrationErrors(
        trans_rmse_norm=float(np.sqrt(np.mean((t - tg) ** 2))),
        rot_euler_rmse_rad=float(euler_rmse(R, Rg)),
        scale_abs=abs(s - sg),
        rot_geodesic_rad=float(geodesic_angle(Rg.T @ R)),
        trans_m=trans_m,
        trans_rel_diag=trans_m / diag,
        scale_rel=abs(s / sg - 1.0),
        add_m=add_m,
        add_rel=add_m / diag,
        trans_rmse_norm_sym=_min_over_symmetry(trans_rmse, symmetry),
        rot_euler_rmse_sym_rad=_min_over_symmetry(rot_euler, symmetry),
        rot_geodesic_sym_rad=_min_over_symmetry(rot_geo, symmetry),
        trans_m_sym=trans_m_sym,
        trans_rel_diag_sym=trans_m_sym / diag,
        add_m_sym=add_m_sym,
        add_rel_sym=add_m_sym / diag,
    )


BARS = {"rot_geodesic_sym_rad": 0.02, "trans_rel_diag_sym": 0.01, "scale_rel": 0.01}
"""A registration is within the bars when its symmetry-aware rotation error (rad), centre error
(fraction of the object's diagonal) and relative scale error are all at most these."""


def within_bars(row: dict, bars: Mapping[str, float] = BARS) -> bool:
    """Whether a (right-object) row's errors are all within ``bars`` (default :data:`BARS`; the
    sensor benchmark widens them by the map's own error)."""
    return all(row[k] is not None and row[k] <= v for k, v in bars.items())
