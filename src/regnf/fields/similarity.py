"""7-DoF similarity transforms ``y = s R x + t`` as 4x4 matrices (float64).

Every frame change in regnf (field -> world, scene -> library, child -> parent) is a
similarity, and SDFs scale with it, so the scale must stay uniform and positive. These two
helpers build such a matrix and take one apart, refusing anything that is not a similarity
(shear, non-uniform or negative scale, reflection). Both accept numpy arrays or torch
tensors and answer in the same library; torch inputs keep autograd through
:func:`similarity_matrix`.
"""

from __future__ import annotations

import numpy as np
import torch

from regnf.captures.model import POSE_RTOL, similarity_scale
from regnf.core.errors import RegnfError

Array = np.ndarray | torch.Tensor

DEFAULT_RTOL = POSE_RTOL
"""Relative tolerance on ``A^T A = s^2 I`` and on the last row; loose enough for float32 input
(the capture loader's :data:`regnf.captures.model.POSE_RTOL`)."""


def _is_torch(*xs: object) -> bool:
    return any(isinstance(x, torch.Tensor) for x in xs)


def similarity_matrix(R: Array, t: Array | None = None, s: float | Array = 1.0) -> Array:
    """The 4x4 matrix of ``y = s R x + t``.

    Parameters
    ----------
    R : (3, 3) float
        Rotation (not checked here; :func:`decompose_similarity` validates).
    t : (3,) float, optional
        Translation; zero by default.
    s : float or () float
        Uniform scale, > 0.

    Returns
    -------
    (4, 4) float64
        A torch tensor (on ``R``'s device, differentiable) if any input is a tensor,
        otherwise a numpy array.
    """
    if _is_torch(R, t, s):
        ref = next(x for x in (R, t, s) if isinstance(x, torch.Tensor))
        dev = ref.device
        Rt = torch.as_tensor(R, dtype=torch.float64, device=dev)
        tt = (
            torch.zeros(3, dtype=torch.float64, device=dev)
            if t is None
            else torch.as_tensor(t, dtype=torch.float64, device=dev)
        )
        st = torch.as_tensor(s, dtype=torch.float64, device=dev)
        s_val = float(st.detach().reshape(-1)[0]) if st.numel() == 1 else None
        _check_parts(tuple(Rt.shape), tuple(tt.shape), s_val, st.numel())
        top = torch.cat([st * Rt, tt.reshape(3, 1)], dim=1)
        bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64, device=dev)
        return torch.cat([top, bottom], dim=0)
    Rn = np.asarray(R, dtype=np.float64)
    tn = np.zeros(3) if t is None else np.asarray(t, dtype=np.float64)
    sn = np.asarray(s, dtype=np.float64)
    s_val = float(sn.reshape(-1)[0]) if sn.size == 1 else None
    _check_parts(Rn.shape, tn.shape, s_val, sn.size)
    M = np.eye(4)
    M[:3, :3] = float(sn) * Rn
    M[:3, 3] = tn.reshape(3)
    return M


def _check_parts(r_shape: tuple, t_shape: tuple, s: float | None, s_size: int) -> None:
    if r_shape != (3, 3):
        raise RegnfError(f"R must be 3x3, got shape {r_shape}")
    if t_shape not in ((3,), (3, 1)):
        raise RegnfError(f"t must have 3 entries, got shape {t_shape}")
    if s_size != 1 or s is None:
        raise RegnfError("s must be a single uniform scale")
    if not np.isfinite(s) or s <= 0:
        raise RegnfError(f"scale must be finite and > 0, got {s}")


def decompose_similarity(M: Array, rtol: float = DEFAULT_RTOL) -> tuple[Array, Array, Array]:
    """Split a similarity ``M = [[s R, t], [0, 1]]`` into ``(R, t, s)``.

    Parameters
    ----------
    M : (4, 4) float
        The matrix; numpy or torch.
    rtol : float
        Relative tolerance of the checks below.

    Returns
    -------
    R : (3, 3) float64
        Rotation, ``R = A / s`` exactly (not re-orthonormalised, so that the round trip
        through :func:`similarity_matrix` is exact).
    t : (3,) float64
    s : () float64
        Same library (and device) as ``M``.

    Raises
    ------
    ValueError
        If ``M`` is not 4x4 and finite, its last row is not ``[0, 0, 0, 1]``, its linear part
        reflects (negative determinant: reflection or negative scale), or it is not a
        uniformly scaled rotation (non-uniform scale or shear).
    """
    as_torch = isinstance(M, torch.Tensor)
    Mt = torch.as_tensor(M, dtype=torch.float64) if not as_torch else M.to(torch.float64)
    if Mt.shape != (4, 4):
        raise RegnfError(f"a similarity must be 4x4, got shape {tuple(Mt.shape)}")
    # One rule for every similarity in regnf (captures, cameras, fields): the checks live at
    # the bottom of the package graph, in synthetic, and run on a float64 copy.
    similarity_scale(Mt.detach().cpu().numpy(), rtol)
    A = Mt[:3, :3]
    s = torch.linalg.det(A) ** (1.0 / 3.0)
    R, t = A / s, Mt[:3, 3]
    if as_torch:
        return R, t.clone(), s
    return R.numpy(), t.numpy().copy(), s.numpy()


def cross_matrices(w: torch.Tensor) -> torch.Tensor:
    """(n, 3, 3) cross-product matrices ``[w]_x`` of vectors ``w`` (n, 3)."""
    z = torch.zeros_like(w[:, 0])
    return torch.stack([
        torch.stack([z, -w[:, 2], w[:, 1]], dim=-1),
        torch.stack([w[:, 2], z, -w[:, 0]], dim=-1),
        torch.stack([-w[:, 1], w[:, 0], z], dim=-1),
    ], dim=-2)
