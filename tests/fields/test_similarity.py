"""Similarity transforms: compose/decompose round trips and rejection of non-similarities."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from regnf.fields.similarity import decompose_similarity, similarity_matrix


@pytest.mark.parametrize("s", [1e-3, 0.25, 1.0, 4.0, 250.0])
def test_round_trip_numpy(s: float) -> None:
    rng = np.random.default_rng(0)
    R = Rotation.random(random_state=1).as_matrix()
    t = rng.normal(size=3) * 10
    M = similarity_matrix(R, t, s)
    assert isinstance(M, np.ndarray) and M.dtype == np.float64 and M.shape == (4, 4)
    # Independent check of the layout: M x = s R x + t.
    x = rng.normal(size=3)
    np.testing.assert_allclose(M[:3, :3] @ x + M[:3, 3], s * R @ x + t, atol=1e-12)
    np.testing.assert_array_equal(M[3], [0, 0, 0, 1])
    R2, t2, s2 = decompose_similarity(M)
    assert isinstance(R2, np.ndarray)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    assert abs(float(s2) - s) <= 1e-12 * max(1.0, s)
    np.testing.assert_allclose(similarity_matrix(R2, t2, s2), M, atol=1e-12)


def test_round_trip_torch_and_grad() -> None:
    R = torch.as_tensor(Rotation.random(random_state=2).as_matrix())
    t = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    s = torch.tensor(2.5, dtype=torch.float64, requires_grad=True)
    M = similarity_matrix(R, t, s)
    assert isinstance(M, torch.Tensor) and M.dtype == torch.float64
    M.sum().backward()  # differentiable in s
    assert s.grad is not None and torch.isclose(s.grad, R.sum())
    R2, t2, s2 = decompose_similarity(M.detach())
    assert isinstance(R2, torch.Tensor)
    assert torch.allclose(R2, R, atol=1e-12) and torch.allclose(t2, t, atol=1e-12)
    assert abs(float(s2) - 2.5) < 1e-12


def test_default_translation_and_scale() -> None:
    M = similarity_matrix(np.eye(3))
    np.testing.assert_array_equal(M, np.eye(4))


@pytest.mark.parametrize(
    "linear",
    [
        np.diag([1.0, 2.0, 1.0]),  # non-uniform scale
        np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # shear
        np.diag([1.0, 1.0, -1.0]),  # reflection
        -2.0 * np.eye(3),  # negative scale
        np.zeros((3, 3)),  # degenerate
    ],
)
def test_rejects_non_similarities(linear: np.ndarray) -> None:
    M = np.eye(4)
    M[:3, :3] = linear
    with pytest.raises(ValueError):
        decompose_similarity(M)
    with pytest.raises(ValueError):
        decompose_similarity(torch.as_tensor(M))


def test_rejects_bad_shapes_and_rows() -> None:
    with pytest.raises(ValueError, match="4x4"):
        decompose_similarity(np.eye(3))
    M = np.eye(4)
    M[3, 0] = 0.5
    with pytest.raises(ValueError, match="last row"):
        decompose_similarity(M)
    M = np.eye(4)
    M[0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        decompose_similarity(M)
    with pytest.raises(ValueError, match="scale"):
        similarity_matrix(np.eye(3), np.zeros(3), -1.0)
    with pytest.raises(ValueError, match="scale"):
        similarity_matrix(np.eye(3), np.zeros(3), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="3x3"):
        similarity_matrix(np.eye(4), np.zeros(3), 1.0)
