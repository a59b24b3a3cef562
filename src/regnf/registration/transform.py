"""The result type of registration: a 7-DoF similarity ``y = s R x + t`` (float64 numpy).

Registration estimates T: scene field frame -> library field frame (docs/design.md section 2).
The USD stage stores the inverse, object -> scene.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from regnf.fields.similarity import decompose_similarity, similarity_matrix


class SimilarityTransform(NamedTuple):
    """``y = s R x + t`` with ``R`` (3, 3) a rotation, ``t`` (3,), ``s`` > 0."""

    R: np.ndarray
    t: np.ndarray
    s: float

    @staticmethod
    def identity() -> SimilarityTransform:
        return SimilarityTransform(np.eye(3), np.zeros(3), 1.0)

    @staticmethod
    def from_matrix(M: np.ndarray) -> SimilarityTransform:
        """Decompose a 4x4 similarity (raises ValueError for shear, reflection, bad scale)."""
        R, t, s = decompose_similarity(np.asarray(M, dtype=np.float64))
        return SimilarityTransform(np.asarray(R), np.asarray(t), float(s))

    def matrix(self) -> np.ndarray:
        """(4, 4) float64."""
        return np.asarray(similarity_matrix(np.asarray(self.R), np.asarray(self.t), float(self.s)))

    def inverse(self) -> SimilarityTransform:
        """``x = (1/s) R^T (y - t)``."""
        Rt = np.asarray(self.R).T
        return SimilarityTransform(Rt, -(Rt @ np.asarray(self.t)) / self.s, 1.0 / self.s)

    def compose(self, other: SimilarityTransform) -> SimilarityTransform:
        """``self ∘ other``: apply ``other`` first."""
        R = np.asarray(self.R) @ np.asarray(other.R)
        t = self.s * (np.asarray(self.R) @ np.asarray(other.t)) + np.asarray(self.t)
        return SimilarityTransform(R, t, self.s * other.s)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Map points (n, 3)."""
        return self.s * (np.asarray(x) @ np.asarray(self.R).T) + np.asarray(self.t)

    def to_json(self) -> dict:
        return {"R": np.asarray(self.R).tolist(), "t": np.asarray(self.t).tolist(), "s": float(self.s),
                "matrix": self.matrix().tolist()}

    @staticmethod
    def from_json(data: dict) -> SimilarityTransform:
        return SimilarityTransform.from_matrix(np.asarray(data["matrix"], dtype=np.float64))
