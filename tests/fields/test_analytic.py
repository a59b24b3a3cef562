"""Analytic SDF fields against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from regnf.fields.analytic import (
    Box,
    Capsule,
    Cylinder,
    RoundedBox,
    SmoothUnion,
    Sphere,
    Transformed,
    Union,
)
from regnf.fields.field import Field
from regnf.fields.similarity import similarity_matrix

SQ2, SQ3 = math.sqrt(2.0), math.sqrt(3.0)


def _sdf(field: Field, pts: list[list[float]]) -> np.ndarray:
    return field.sdf(torch.tensor(pts, dtype=torch.float64)).numpy()


def _check(field: Field, cases: list[tuple[list[float], float]]) -> None:
    got = _sdf(field, [p for p, _ in cases])
    np.testing.assert_allclose(got, [v for _, v in cases], atol=1e-12)


def test_sphere_closed_form() -> None:
    c = np.array([0.3, -0.2, 0.5])
    f = Sphere(0.7, c)
    _check(
        f,
        [
            (list(c), -0.7),
            (list(c + [0.7, 0, 0]), 0.0),
            (list(c + [0, 3.0, 0]), 2.3),
            (list(c + [0.1, 0, 0]), -0.6),
            (list(c + [1, 1, 1]), SQ3 - 0.7),
        ],
    )


def test_box_closed_form() -> None:
    c = np.array([1.0, 2.0, -1.0])
    f = Box((1.0, 2.0, 3.0), c)
    _check(
        f,
        [
            (list(c + [2, 0, 0]), 1.0),  # face
            (list(c + [2, 3, 4]), SQ3),  # corner region
            (list(c + [2, 3, 0]), SQ2),  # edge region
            (list(c + [0.5, 0, 0]), -0.5),  # inside, nearest face x
            (list(c), -1.0),
            (list(c + [1.0, 0.5, 0.5]), 0.0),  # on a face
            (list(c + [-1.0, -2.0, -3.0]), 0.0),  # a corner
            (list(c + [0.2, -1.9, 0.1]), -0.1),  # inside, nearest face y
        ],
    )


def test_rounded_box_closed_form() -> None:
    f = RoundedBox((1.0, 1.0, 2.0), 0.25)
    _check(
        f,
        [
            ([2, 0, 0], 1.0),  # the faces stay at the outer half extents
            ([0, 0, 2], 0.0),
            ([2, 2, 3], SQ3 * 1.25 - 0.25),  # corner: distance to the rounded corner's sphere
            ([1, 1, 0], SQ2 * 0.25 - 0.25),  # the sharp edge is outside the rounded one
            ([0, 0, 0], -1.0),
        ],
    )


def test_cylinder_closed_form() -> None:
    f = Cylinder(1.0, 2.0, center=(0.0, 0.0, 1.0))
    _check(
        f,
        [
            ([3, 0, 1], 2.0),  # side
            ([0, 0, 6], 3.0),  # cap
            ([0, 0, -2], 1.0),  # bottom cap
            ([2, 0, 4], SQ2),  # rim
            ([0, 0, 1], -1.0),  # centre: nearest is the side
            ([0, 0, 2.5], -0.5),  # nearest is the top cap
            ([0.6, 0.8, 1], 0.0),  # on the side
        ],
    )


def test_capsule_closed_form() -> None:
    f = Capsule((0.0, 0.0, 0.0), (0.0, 0.0, 2.0), 0.5)
    _check(
        f,
        [
            ([1, 0, 1], 0.5),
            ([0, 0, 3], 0.5),  # beyond b
            ([0, 0, -1], 0.5),  # beyond a
            ([0, 0, 1], -0.5),
            ([1, 0, 3], SQ2 - 0.5),
            ([0, 0.5, 2.5 / SQ2 + 2], 0.0 + math.hypot(0.5, 2.5 / SQ2) - 0.5),
        ],
    )
    sphere_like = Capsule((1.0, 1.0, 1.0), (1.0, 1.0, 1.0), 0.5)
    _check(sphere_like, [([1, 1, 3], 1.5), ([1, 1, 1], -0.5)])


PRIMITIVES = {
    "sphere": Sphere(0.6, (0.1, 0.0, -0.1)),
    "box": Box((0.5, 0.3, 0.7), (0.0, 0.1, 0.0)),
    "rounded_box": RoundedBox((0.5, 0.3, 0.7), 0.1),
    "cylinder": Cylinder(0.4, 0.6),
    "capsule": Capsule((-0.3, 0.0, 0.0), (0.3, 0.2, 0.1), 0.3),
}
INSIDE_EXACT = {"sphere", "box", "capsule", "rounded_box", "cylinder"}


@pytest.mark.parametrize("name", list(PRIMITIVES))
def test_gradient_norm_is_one(name: str) -> None:
    f = PRIMITIVES[name]
    gen = torch.Generator().manual_seed(0)
    x = (torch.rand(4000, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 1.5
    s, g = f.sdf_and_gradient(x)
    norm = torch.linalg.vector_norm(g, dim=-1)
    out = s > 1e-3
    assert out.sum() > 100
    assert torch.allclose(norm[out], torch.ones_like(norm[out]), atol=1e-4)
    if name in INSIDE_EXACT:
        inside = s < -1e-3
        assert inside.sum() > 20
        assert torch.allclose(norm[inside], torch.ones_like(norm[inside]), atol=1e-4)


@pytest.mark.parametrize("name", list(PRIMITIVES))
def test_bounds_tight_and_containing(name: str) -> None:
    f = PRIMITIVES[name]
    gen = torch.Generator().manual_seed(1)
    x = (torch.rand(20000, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 1.5
    inside = x[f.sdf(x) <= 0].float()
    assert inside.shape[0] > 100
    assert bool(f.contains(inside).all())
    lo, hi = inside.min(0).values, inside.max(0).values
    # Tight: the padding is a few percent of the size, not more.
    assert bool(((f.bounds[1] - f.bounds[0]) <= 1.15 * (hi - lo) + 0.05).all())


def test_constant_color_and_buffers() -> None:
    f = Sphere(1.0, color=(0.1, 0.2, 0.3), label="ball", name="b1")
    x = torch.zeros(4, 3)
    c = f.color(x, torch.ones(4, 3))
    assert c.shape == (4, 3) and c.dtype == torch.float32
    assert torch.allclose(c, torch.tensor([0.1, 0.2, 0.3]).expand(4, 3))
    assert f.info.label == "ball" and f.info.name == "b1"
    buffers = dict(f.named_buffers())
    assert {"radius", "center", "rgb", "bounds", "to_world"} <= set(buffers)
    g = f.to(torch.device("cpu"))
    assert g.device == torch.device("cpu")
    assert f.sdf(torch.zeros(1, 3)).dtype == torch.float32


def test_bad_parameters_raise() -> None:
    with pytest.raises(ValueError, match="radius"):
        Sphere(-1.0)
    with pytest.raises(ValueError, match="center"):
        Sphere(1.0, (0.0, 0.0))
    with pytest.raises(ValueError, match="color"):
        Sphere(1.0, color=(1.2, 0.0, 0.0))
    with pytest.raises(ValueError, match="half_extents"):
        Box((1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="radius"):
        RoundedBox((1.0, 0.2, 1.0), 0.3)
    with pytest.raises(ValueError, match="at least one"):
        Union()
    with pytest.raises(ValueError, match="k"):
        SmoothUnion(Sphere(), k=0.0)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        Sphere().sdf(torch.zeros(3))


def test_union_values_and_color() -> None:
    a = Sphere(0.5, (-1.0, 0.0, 0.0), color=(1.0, 0.0, 0.0))
    b = Box((0.5, 0.5, 0.5), (1.0, 0.0, 0.0), color=(0.0, 0.0, 1.0))
    u = Union(a, b, label="pair")
    # Sphere centre, box centre, nearer the sphere (0.3 vs 0.7), nearer the box (0.7 vs 0.3).
    pts = [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-0.2, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 3.0, 0.0]]
    x = torch.tensor(pts, dtype=torch.float64)
    np.testing.assert_allclose(u.sdf(x).numpy(), torch.minimum(a.sdf(x), b.sdf(x)).numpy())
    np.testing.assert_allclose(u.sdf(x).numpy()[:4], [-0.5, -0.5, 0.3, 0.3], atol=1e-12)
    col = u.color(x).numpy()
    np.testing.assert_allclose(col[[0, 2]], [[1, 0, 0]] * 2)
    np.testing.assert_allclose(col[[1, 3]], [[0, 0, 1]] * 2)
    assert bool((u.bounds[0] <= torch.minimum(a.bounds[0], b.bounds[0])).all())
    assert bool((u.bounds[1] >= torch.maximum(a.bounds[1], b.bounds[1])).all())
    assert u.info.label == "pair"


def test_smooth_union_values_and_blend() -> None:
    k = 0.4
    a = Sphere(0.5, (-1.0, 0.0, 0.0), color=(1.0, 0.0, 0.0))
    b = Sphere(0.5, (1.0, 0.0, 0.0), color=(0.0, 0.0, 1.0))
    su = SmoothUnion(a, b, k=k)
    # Midway: both distances are 0.5, so smin = 0.5 - k / 4 and the colours mix 50/50.
    mid = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)
    np.testing.assert_allclose(su.sdf(mid).numpy(), [0.5 - k / 4], atol=1e-12)
    np.testing.assert_allclose(su.color(mid).numpy(), [[0.5, 0.0, 0.5]], atol=1e-12)
    # Far from the blend (|da - db| >= k): exactly the hard union and the winner's colour.
    far = torch.tensor([[-1.0, 0.0, 0.0], [1.2, 0.3, 0.0]], dtype=torch.float64)
    hard = torch.minimum(a.sdf(far), b.sdf(far))
    np.testing.assert_allclose(su.sdf(far).numpy(), hard.numpy(), atol=1e-12)
    np.testing.assert_allclose(su.color(far).numpy(), [[1, 0, 0], [0, 0, 1]], atol=1e-12)
    # Everywhere: hard - k/4 <= smooth <= hard.
    x = (
        torch.rand(2000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 3
        - 1.5
    )
    hard, soft = torch.minimum(a.sdf(x), b.sdf(x)), su.sdf(x)
    assert bool((soft <= hard + 1e-12).all()) and bool((soft >= hard - k / 4 - 1e-12).all())
    assert float(su.bounds[1, 0]) >= 1.5 + k / 4


class DirColor(Field):
    """Test field: a unit sphere whose colour encodes the view direction."""

    def __init__(self) -> None:
        super().__init__(torch.tensor([[-1.1] * 3, [1.1] * 3]))

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return torch.linalg.vector_norm(x, dim=-1) - 1.0

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        return 0.5 * (d + 1.0)


def _random_similarity(s: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.random.default_rng(seed).normal(size=3)
    return R, t, similarity_matrix(R, t, s)


@pytest.mark.parametrize("s", [0.25, 1.0, 4.0])
def test_transformed_matches_scaled_child(s: float) -> None:
    child = Box((0.5, 0.2, 0.3), (0.1, 0.0, 0.2), color=(0.2, 0.4, 0.6))
    _, t, M = _random_similarity(s, seed=3)
    f = Transformed(child, M)
    Minv = np.linalg.inv(M)
    y = np.random.default_rng(4).normal(size=(500, 3)) * 2 * s + t
    x_child = y @ Minv[:3, :3].T + Minv[:3, 3]
    expect = s * child.sdf(torch.as_tensor(x_child)).numpy()
    np.testing.assert_allclose(f.sdf(torch.as_tensor(y)).numpy(), expect, atol=1e-10)
    # Gradient of an exact SDF stays unit under a similarity.
    _, g = f.sdf_and_gradient(torch.as_tensor(y))
    assert torch.allclose(
        torch.linalg.vector_norm(g, dim=-1), torch.ones(500, dtype=torch.float64), atol=1e-4
    )
    # Bounds contain the mapped child surface (sampled densely inside the child).
    xs = torch.rand(20000, 3, dtype=torch.float64) * 2 - 1
    xs = xs[child.sdf(xs) <= 0].numpy()
    ys = xs @ M[:3, :3].T + M[:3, 3]
    assert bool(f.contains(torch.as_tensor(ys, dtype=torch.float32), pad=1e-5).all())
    np.testing.assert_allclose(f.color(torch.as_tensor(y)).numpy(), [[0.2, 0.4, 0.6]] * 500)


@pytest.mark.parametrize("s", [0.25, 1.0, 4.0])
def test_transformed_sphere_is_closed_form_sphere(s: float) -> None:
    c, r = np.array([0.3, -0.1, 0.2]), 0.4
    R, t, M = _random_similarity(s, seed=5)
    f = Transformed(Sphere(r, c), M)
    c_new = s * R @ c + t
    y = np.random.default_rng(6).normal(size=(300, 3)) * s + c_new
    expect = np.linalg.norm(y - c_new, axis=1) - s * r
    np.testing.assert_allclose(f.sdf(torch.as_tensor(y)).numpy(), expect, atol=1e-10)
    assert bool((f.bounds[0].double() <= torch.as_tensor(c_new - s * r)).all())
    assert bool((f.bounds[1].double() >= torch.as_tensor(c_new + s * r)).all())


def test_transformed_rotates_view_direction() -> None:
    R, _, M = _random_similarity(2.0, seed=7)
    f = Transformed(DirColor(), M)
    y = torch.randn(50, 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    expect = 0.5 * (d.numpy() @ R + 1.0)  # child sees R^T d
    np.testing.assert_allclose(f.color(y, d).numpy(), expect, atol=1e-12)


def test_transformed_rejects_bad_matrices() -> None:
    child = Sphere(1.0)
    for lin in (
        np.diag([1.0, 2.0, 1.0]),
        np.diag([-1.0, 1.0, 1.0]),
        -np.eye(3),
        np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
    ):
        M = np.eye(4)
        M[:3, :3] = lin
        with pytest.raises(ValueError):
            Transformed(child, M)
    with pytest.raises(ValueError):
        Transformed(child, np.eye(3))
    with pytest.raises(TypeError):
        Transformed("not a field", np.eye(4))  # type: ignore[arg-type]
