"""The sphere tracer of any field against closed-form ray intersections, in the field frame:
with registration's sampling settings (under-relaxed, bisection) and with the renderer's
(relaxed, grid skipping, Illinois)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from regnf.core.cameras import pinhole_rays
from regnf.fields.analytic import Box, Sphere, Union
from regnf.fields.field import Field
from regnf.registration.sampling import SAMPLING_TRACE
from regnf.render.sphere_tracer import (
    SphereTracerConfig,
    TraceHits,
    trace,
)

CPU = torch.device("cpu")


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world pose (x right, y down, z forward) at ``eye`` facing ``target``."""
    up = np.array([0.0, 0.0, 1.0])
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    C = np.eye(4)
    C[:3, :3] = np.stack([x, y, z], axis=1)
    C[:3, 3] = eye
    return C


def intrinsics(f: float, w: int, h: int) -> np.ndarray:
    return np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])


class ScaledSDF(Field):
    """A "neural-like" field: a true SDF times a constant, so not a distance any more."""

    def __init__(self, child: Field, factor: float) -> None:
        super().__init__(child.bounds.clone())
        self.child, self.factor = child, factor
        self.evaluated = 0  # points evaluated so far

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        self.evaluated += x.shape[0]
        return self.factor * self.child.sdf(x)

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        return self.child.color(x, d)


def ray_sphere(
    o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed form: (hit, t, discriminant) of unit rays with a sphere, first hit in front."""
    oc = o - c
    b = np.einsum("ij,ij->i", d, oc)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return (disc > 0) & (t > 0), t, disc


def frontal(disc: np.ndarray, r: float, min_cos: float = 0.2) -> np.ndarray:
    """Rays meeting the sphere at incidence cosine >= ``min_cos``.

    The tracer's tolerance is on |sdf|, so its error along the ray is tol / cos(incidence):
    near the silhouette a 1e-5 SDF tolerance is more than 1e-4 in t.
    """
    return np.maximum(disc, 0.0) >= (min_cos * r) ** 2


def ray_box(
    o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed form: (hit, t_in, chord length) of rays with the box [lo, hi], hit in front."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t_in = np.minimum(ta, tb).max(axis=1)
    t_out = np.maximum(ta, tb).min(axis=1)
    return (t_in < t_out) & (t_in > 0), t_in, t_out - t_in


CONFIGS = {"sampling": SAMPLING_TRACE, "render": SphereTracerConfig()}
"""Registration's settings and the renderer's defaults: both must find the same surfaces."""


def _trace_camera(
    field: Field,
    eye: np.ndarray,
    target: np.ndarray,
    n: int = 64,
    f: float = 60.0,
    config: SphereTracerConfig = SAMPLING_TRACE,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, TraceHits]:
    o, d, z = pinhole_rays(intrinsics(f, n, n), look_at(eye, target), n, n, device=CPU)
    return o, d, z, trace(field, o, d, config)


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_sphere_hits_match_closed_form(config: SphereTracerConfig) -> None:
    c, r = np.array([0.1, -0.05, 0.2]), 0.5
    field = Sphere(r, c)
    o, d, _, tr = _trace_camera(field, np.array([2.0, 1.5, 1.0]), c, config=config)
    hit, t_true, disc = ray_sphere(o.double().numpy(), d.double().numpy(), c, r)
    clear = np.abs(disc) > 1e-3  # leave out rays within a hair of the silhouette
    assert hit.sum() > 300 and (~hit).sum() > 300
    np.testing.assert_array_equal(tr.hit.numpy()[clear], hit[clear])
    both = hit & tr.hit.numpy() & frontal(disc, r)
    assert np.abs(tr.t.numpy()[both] - t_true[both]).max() < 1e-4
    assert np.all(np.isinf(tr.t.numpy()[~tr.hit.numpy()]))
    assert torch.all(tr.points[~tr.hit] == 0)
    p = tr.points[tr.hit].double()
    np.testing.assert_allclose(
        torch.linalg.vector_norm(p - torch.as_tensor(c), dim=-1).numpy(), r, atol=1e-4
    )
    assert tr.evals.dtype == torch.long
    assert int(tr.evals[tr.hit].min()) >= 1


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_box_hits_match_closed_form(config: SphereTracerConfig) -> None:
    lo, hi = np.array([-0.4, -0.3, -0.2]), np.array([0.6, 0.3, 0.5])
    field = Box((hi - lo) / 2, (hi + lo) / 2)
    o, d, _, tr = _trace_camera(field, np.array([-1.5, 2.0, 1.3]), np.array([0.1, 0.0, 0.1]),
                                config=config)
    hit, t_true, chord = ray_box(o.double().numpy(), d.double().numpy(), lo, hi)
    clear = ~hit | (chord > 1e-3)  # leave out rays that only graze an edge
    # ...and misses that would hit the box grown by a hair.
    grown_hit, _, _ = ray_box(o.double().numpy(), d.double().numpy(), lo - 1e-3, hi + 1e-3)
    clear &= hit | ~grown_hit
    assert hit.sum() > 300 and (~hit).sum() > 300
    np.testing.assert_array_equal(tr.hit.numpy()[clear], hit[clear])
    both = hit & tr.hit.numpy()
    assert np.abs(tr.t.numpy()[both] - t_true[both]).max() < 1e-4


@pytest.mark.parametrize("factor", [1.5, 0.7])
def test_neural_like_sdf_converges(factor: float) -> None:
    c, r = np.array([0.0, 0.0, 0.0]), 0.6
    exact = Sphere(r, c)
    field = ScaledSDF(exact, factor)
    o, d, _, tr = _trace_camera(field, np.array([0.0, -2.5, 0.4]), c)
    evaluated = field.evaluated
    hit, t_true, disc = ray_sphere(o.double().numpy(), d.double().numpy(), c, r)
    clear = np.abs(disc) > 1e-3
    np.testing.assert_array_equal(tr.hit.numpy()[clear], hit[clear])
    both = hit & tr.hit.numpy() & frontal(disc, r)
    assert np.abs(tr.t.numpy()[both] - t_true[both]).max() < 1e-4
    # The tolerance is met on the field's own (scaled) values.
    assert float(field.sdf(tr.points[tr.hit]).abs().max()) < 2e-5
    assert int(tr.evals[tr.hit].min()) >= 2
    # The reported evaluations are exactly the field evaluations made.
    assert int(tr.evals.sum()) == evaluated
    assert int(tr.evals.max()) <= SAMPLING_TRACE.max_steps + SAMPLING_TRACE.max_refine


def test_steps_zero_outside_bounds_and_near_far() -> None:
    field = Sphere(0.5)
    o = torch.tensor([[0.0, 0.0, -3.0], [5.0, 0.0, -3.0], [0.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    cfg = SAMPLING_TRACE
    tr = trace(field, o, d, cfg)
    assert tr.hit.tolist() == [True, False, False]
    assert abs(float(tr.t[0]) - 2.5) < 1e-5
    assert tr.evals.tolist()[1:] == [0, 0]  # the slab test rejects them for free
    # far before the surface, near past it (metres; this field's frame is in metres).
    assert not bool(trace(field, o[:1], d[:1], dataclasses.replace(cfg, far=2.0)).hit[0])
    tr_near = trace(field, o[:1], d[:1], dataclasses.replace(cfg, near=3.0))  # starts inside
    assert bool(tr_near.hit[0]) and abs(float(tr_near.t[0]) - 3.0) < 1e-6
    assert not bool(trace(field, o[:1], d[:1], dataclasses.replace(cfg, near=3.6)).hit[0])
    with pytest.raises(ValueError, match="near"):
        dataclasses.replace(cfg, near=2.0, far=1.0)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        trace(field, o, d[:2], cfg)
    empty = trace(field, o[:0], d[:0], cfg)
    assert empty.hit.shape == (0,) and empty.points.shape == (0, 3)


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
@pytest.mark.parametrize("max_steps", [256, 7])
def test_wavefront_trace_equals_one_batch(config: SphereTracerConfig, max_steps: int) -> None:
    # A ray's trace is its own: 100 rays marching at once, the next admitted as each stops,
    # give the bits of all 1024 at once; with 7 steps a ray, rays admitted late get 7 too.
    field = Box((0.4, 0.3, 0.5), (0.0, 0.1, 0.0))
    o, d, _ = pinhole_rays(intrinsics(30.0, 32, 32), look_at(np.array([0.3, -2.0, 0.8]), np.zeros(3)), 32, 32,
                           device=CPU)
    cfg = dataclasses.replace(config, max_steps=max_steps, footprint_fraction=0.05)
    whole = trace(field, o, d, dataclasses.replace(cfg, chunk=o.shape[0]), pixel_angle=1 / 30)
    small = trace(field, o, d, dataclasses.replace(cfg, chunk=100), pixel_angle=1 / 30)
    for a, b in zip(whole, small, strict=True):
        assert torch.equal(a, b)
    assert 100 < int(whole.hit.sum()) < o.shape[0]
    assert int(whole.evals.max()) <= max_steps + cfg.max_refine
    if max_steps == 7:  # some rays ran out of steps: misses, not hits
        assert int(whole.hit.sum()) < int(trace(field, o, d, config, pixel_angle=1 / 30).hit.sum())


def test_t_max_stops_each_ray_before_what_lies_beyond() -> None:
    # Two unit spheres on the x axis, centres at 3 and 6; rays from the origin along +x.
    field = Union(Sphere(1.0, np.array([3.0, 0.0, 0.0])), Sphere(1.0, np.array([6.0, 0.0, 0.0])))
    o = torch.zeros(3, 3)
    d = torch.tensor([[1.0, 0.0, 0.0]] * 3)
    t_min = torch.tensor([0.0, 4.5, 4.5])  # the third ray starts past the first sphere
    t_max = torch.tensor([10.0, 10.0, 4.9])  # and stops before the second
    hits = trace(field, o, d, SphereTracerConfig(grid_resolution=0), t_min=t_min, t_max=t_max)
    assert hits.hit.tolist() == [True, True, False]
    np.testing.assert_allclose(hits.t[:2].numpy(), [2.0, 5.0], atol=1e-4)
    with pytest.raises(ValueError, match="t_max"):
        trace(field, o, d, t_max=torch.zeros(2))
