"""Oriented boxes: an object proposal, a placed object's culling volume, a removal region.

A box is ``{c + R u : |u_k| <= h_k}`` in some outer frame (a field's frame): centre ``c``
(3,), half extents ``h`` (3,) and axes ``R`` (3, 3), whose COLUMNS are the box axes in the
outer frame. In a scene it comes from a detector or, as in the paper, from the data set's
ground-truth box; in a library field it is the whole object. Registration's surface sampling
aims its cameras at it; the compositor culls placed fields to it and cuts removal regions
with its SDF, which is exact (Euclidean distance outside, minus the distance to the nearest
face inside), so 1-Lipschitz and a lower bound of the distance to anything the box contains.
The numbers are float64 numpy arrays; :meth:`OrientedBox.local` and :meth:`OrientedBox.sdf`
take torch points on any device.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.analytic import box_sdf
from regnf.fields.similarity import decompose_similarity

ArrayLike = torch.Tensor | np.ndarray | Sequence[float] | Sequence[Sequence[float]]


def as_float64(value: ArrayLike, shape: tuple[int, ...], what: str) -> torch.Tensor:
    """``value`` as a finite CPU float64 tensor of ``shape``, or a clear ``ValueError``."""
    t = torch.as_tensor(
        value.detach().cpu() if isinstance(value, torch.Tensor) else np.asarray(value),
        dtype=torch.float64,
    )
    if tuple(t.shape) != shape:
        raise RegnfError(f"{what} must have shape {shape}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise RegnfError(f"{what} has non-finite entries: {t.tolist()}")
    return t.clone()


def _numpy(value: ArrayLike | None) -> np.ndarray | None:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().double().numpy()
    return None if value is None else np.asarray(value, dtype=np.float64)


CORNER_RTOL = 1e-6
"""Corners must match a box to this fraction of its diagonal (float32 input passes)."""

_SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))  # (8, 3), x slowest


class _OrientedBoxFields(NamedTuple):
    center: np.ndarray
    """(3,) float64: the box centre."""
    half_extents: np.ndarray
    """(3,) float64: half sizes along the box's own axes, all > 0."""
    rotation: np.ndarray
    """(3, 3) float64: columns are the box axes (a proper rotation, box -> frame)."""


class OrientedBox(_OrientedBoxFields):
    """An oriented box ``{c + R u : |u_i| <= h_i}`` in a field's frame.

    Construction validates: finite entries, positive half extents, ``rotation`` a proper
    rotation. A point ``x`` has box coordinates ``u = R^T (x - c)``.
    """

    __slots__ = ()

    def __new__(  # noqa: PYI034 (typing.Self needs Python 3.11)
        cls,
        center: ArrayLike,
        half_extents: ArrayLike,
        rotation: ArrayLike | None = None,
    ) -> OrientedBox:
        c = _numpy(center).reshape(-1)
        h = _numpy(half_extents).reshape(-1)
        R = np.eye(3) if rotation is None else _numpy(rotation)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise RegnfError(f"box center must be 3 finite numbers, got {c.tolist()}")
        if h.shape != (3,) or not np.isfinite(h).all() or not (h > 0).all():
            raise RegnfError(f"box half_extents must be 3 finite numbers > 0 (a box cannot be empty or "
                             f"flat), got {h.tolist()}")
        if R.shape != (3, 3) or not np.isfinite(R).all():
            raise RegnfError(f"box rotation must be a finite 3x3 matrix, got shape {R.shape}")
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-5 or np.linalg.det(R) <= 0:
            raise RegnfError("box rotation must be a proper rotation (orthonormal, det +1)")
        return super().__new__(cls, c, h, R)

    # -- constructors -------------------------------------------------------------------------
    @staticmethod
    def from_aabb(lo: np.ndarray, hi: np.ndarray) -> OrientedBox:
        """The axis-aligned box ``[lo, hi]`` (each (3,)); raises if any ``hi <= lo``."""
        lo_, hi_ = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if lo_.shape != (3,) or hi_.shape != (3,):
            raise RegnfError(f"lo and hi must be (3,), got {lo_.shape} and {hi_.shape}")
        if not (hi_ > lo_).all():
            raise RegnfError(f"an AABB needs hi > lo on every axis, got lo={lo_}, hi={hi_}")
        return OrientedBox(0.5 * (lo_ + hi_), 0.5 * (hi_ - lo_), np.eye(3))

    @staticmethod
    def from_corners(corners: np.ndarray) -> OrientedBox:
        """The oriented box whose 8 corners are ``corners`` (8, 3), in any order.

        The three edges at one corner are found among its 7 difference vectors as the only
        mutually orthogonal triple that regenerates all 8 corners (no PCA: that is ambiguous
        for boxes with two equal sides). Axes are ordered and signed to be as close to the
        frame's axes as possible, so an axis-aligned box comes back with ``rotation = I``.

        Raises
        ------
        ValueError
            If the array is not (8, 3) and finite, the corners are degenerate (repeated, flat)
            or they are not the corners of a rectangular box.
        """
        P = np.asarray(corners, dtype=np.float64)
        if P.shape != (8, 3) or not np.isfinite(P).all():
            raise RegnfError(f"corners must be a finite (8, 3) array, got shape {P.shape}")
        V = P[1:] - P[0]  # (7, 3)
        diag = float(np.linalg.norm(V, axis=1).max())
        if diag <= 0:
            raise RegnfError("box corners are all the same point")
        tol = CORNER_RTOL * diag * 10
        triples = np.array(list(itertools.combinations(range(7), 3)))  # (35, 3)
        E = V[triples]  # (35, 3, 3): candidate edge triples
        G = np.einsum("kia,kja->kij", E, E)
        off = np.abs(G[:, [0, 0, 1], [1, 2, 2]]).max(axis=1) / diag**2
        order = np.argsort(off, kind="stable")
        for k in order[:4]:  # only near-orthogonal triples can be the answer
            edges = E[k]
            lengths = np.linalg.norm(edges, axis=1)
            if lengths.min() <= tol or off[k] > 1e-5:
                break
            gen = P[0] + (_SIGNS * 0.5 + 0.5) @ edges  # (8, 3): all subset sums
            dist = np.linalg.norm(gen[:, None, :] - P[None, :, :], axis=-1)
            if (dist.min(axis=1) <= tol).all() and (dist.min(axis=0) <= tol).all():
                return OrientedBox._from_edges(P.mean(axis=0), edges)
        raise RegnfError(
            "corners are not the 8 corners of a non-degenerate rectangular box "
            "(repeated or coplanar points, or the angles are not right angles)"
        )

    @staticmethod
    def _from_edges(center: np.ndarray, edges: np.ndarray) -> OrientedBox:
        lengths = np.linalg.norm(edges, axis=1)
        axes = edges / lengths[:, None]  # rows: unit box axes
        # Pick the permutation and signs that bring the axes closest to x, y, z.
        best = max(
            itertools.permutations(range(3)),
            key=lambda p: sum(abs(axes[p[i], i]) for i in range(3)),
        )
        A = axes[list(best)]
        A = A * np.where(np.diag(A) < 0, -1.0, 1.0)[:, None]
        R = A.T  # columns = axes
        if np.linalg.det(R) < 0:  # keep right-handed: flip the axis least aligned
            j = int(np.argmin(np.abs(np.diag(R))))
            R[:, j] = -R[:, j]
        # Re-orthonormalise (the corners may be float32): polar decomposition by SVD.
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
        return OrientedBox(center, 0.5 * lengths[list(best)], R)

    @staticmethod
    def from_bounds(bounds: torch.Tensor, matrix: ArrayLike) -> OrientedBox:
        """The image of the AABB ``bounds`` (2, 3) under the similarity ``matrix`` (4, 4).

        A similarity maps a box to a box: centre ``s R c + t``, half extents ``s h``, axes ``R``.
        """
        M = as_float64(matrix, (4, 4), "similarity matrix")
        R, t, s = decompose_similarity(M)
        lo, hi = bounds.detach().cpu().double()
        return OrientedBox(s * (R @ (0.5 * (lo + hi))) + t, s * 0.5 * (hi - lo), R)

    # -- derived quantities ------------------------------------------------------------------
    @property
    def radius(self) -> float:
        """Half the diagonal: the radius of the sphere through the corners."""
        return float(np.linalg.norm(self.half_extents))

    @property
    def diagonal(self) -> float:
        """Length of the box diagonal."""
        return 2.0 * self.radius

    def corners(self) -> np.ndarray:
        """(8, 3) float64 corners, box-axis signs in ``itertools.product`` order."""
        return self.center + (_SIGNS * self.half_extents) @ self.rotation.T

    def inflated(self, pad_rel: float) -> OrientedBox:
        """The same box with every half extent grown by the fraction ``pad_rel`` (> -1)."""
        if not np.isfinite(pad_rel) or pad_rel <= -1:
            raise RegnfError(f"pad_rel must be finite and > -1, got {pad_rel}")
        return OrientedBox(self.center, self.half_extents * (1.0 + pad_rel), self.rotation)

    def transformed(self, M: np.ndarray) -> OrientedBox:
        """The box mapped by the 4x4 similarity ``M`` (for example metres -> scene field frame).

        Raises ``ValueError`` if ``M`` is not a similarity (shear, reflection, ...).
        """
        R, t, s = decompose_similarity(np.asarray(M, dtype=np.float64))
        R = np.asarray(R)
        return OrientedBox(
            float(s) * (R @ self.center) + np.asarray(t),
            float(s) * self.half_extents,
            R @ self.rotation,
        )

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """Box coordinates ``R^T (x - c)`` (n, 3) of ``points`` (n, 3)."""
        return (np.asarray(points, dtype=np.float64) - self.center) @ self.rotation

    def local(self, x: torch.Tensor) -> torch.Tensor:
        """Box coordinates ``R^T (x - c)`` (n, 3) of torch points ``x`` (n, 3), in their dtype."""
        c = torch.as_tensor(self.center, dtype=x.dtype, device=x.device)
        return (x - c) @ torch.as_tensor(self.rotation, dtype=x.dtype, device=x.device)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Exact signed distance (n,) of torch points ``x`` (n, 3) to the box, outer-frame units."""
        return box_sdf(self.local(x), torch.as_tensor(self.half_extents, dtype=x.dtype,
                                                      device=x.device))

    def aabb(self) -> torch.Tensor:
        """(2, 3) float64 axis-aligned bounds of the box in the outer frame (a CPU tensor)."""
        # The half size of a rotated box along outer axis k is sum_j |R_kj| h_j.
        half = torch.from_numpy(self.rotation).abs() @ torch.from_numpy(self.half_extents)
        c = torch.from_numpy(self.center)
        return torch.stack([c - half, c + half])

    def contains(self, points: np.ndarray, pad_rel: float = 0.0) -> np.ndarray:
        """(n,) bool: ``points`` (n, 3) inside the box with half extents grown by ``pad_rel``."""
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise RegnfError(f"points must be (n, 3), got shape {p.shape}")
        return (np.abs(self.to_local(p)) <= self.half_extents * (1.0 + pad_rel)).all(axis=1)

    def to_json(self) -> dict:
        return {
            "center": self.center.tolist(),
            "half_extents": self.half_extents.tolist(),
            "rotation": self.rotation.tolist(),
        }

    @staticmethod
    def from_json(data: dict) -> OrientedBox:
        return OrientedBox(
            np.asarray(data["center"]),
            np.asarray(data["half_extents"]),
            np.asarray(data["rotation"]),
        )


class OrientedBoxes(torch.nn.Module):
    """Several oriented boxes whose signed distances are evaluated at once.

    A composite asks for the distance to every placed object's box, and to every removal box, at
    each sphere-tracing step: one matrix product for all of them, instead of a few small kernels
    per box, cuts the interpreter's share of a step, which is what limits two views traced side
    by side on two threads (docs/decisions/rendering-speed.md).

    Parameters
    ----------
    boxes : sequence of OrientedBox
        At least one.
    """

    def __init__(self, boxes: Sequence[OrientedBox]) -> None:
        super().__init__()
        if not boxes:
            raise RegnfError("OrientedBoxes needs at least one box")
        R = np.stack([b.rotation for b in boxes])  # (k, 3, 3), columns the box axes
        C = np.stack([b.center for b in boxes])
        # x R_k - c_k R_k for every k from one product with the (3, 3k) block row [R_0 R_1 ...].
        self.register_buffer("axes", torch.from_numpy(R.transpose(1, 0, 2).reshape(3, -1).copy()), persistent=False)
        self.register_buffer("offsets", torch.from_numpy(np.einsum("ki,kij->kj", C, R).reshape(-1)), persistent=False)
        self.register_buffer("half_extents", torch.from_numpy(np.stack([b.half_extents for b in boxes])),
                             persistent=False)

    def __len__(self) -> int:
        return int(self.half_extents.shape[0])

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Exact signed distances (k, n) of points ``x`` (n, 3) to each box, in ``x``'s dtype."""
        local = (x @ self.axes.to(x.dtype) - self.offsets.to(x.dtype)).view(x.shape[0], len(self), 3)
        q = local.abs() - self.half_extents.to(x.dtype)
        d = torch.linalg.vector_norm(q.clamp(min=0.0), dim=-1) + q.max(dim=-1).values.clamp(max=0.0)
        return d.T.contiguous()
