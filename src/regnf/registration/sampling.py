"""Multi-view surface sampling of a field around an object proposal (docs/design.md section 1.2).

Virtual pinhole cameras on a sphere around the proposal box look at its centre; a grid of
rays per camera (through pixel centres) is sphere-traced and bisected to the surface. On the
SCENE side rays start where they enter the inflated box (walls and other furniture between a
virtual camera and the object are not occluders: only the surface inside the box is wanted),
hits outside the inflated box are dropped and the supporting floor is removed with a plane
fit. On the LIBRARY side every hit is kept. Points are voxel-downsampled and capped.

The camera distance and field of view are relative to the box (the authors' code used an
absolute distance, which breaks for fields of another scale).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import torch

from regnf.core.cameras import pinhole_rays, ray_aabb
from regnf.core.errors import RegnfError
from regnf.fields.field import DEFAULT_CHUNK, Field
from regnf.fields.oriented_box import OrientedBox
from regnf.render.sphere_tracer import SphereTracerConfig, trace

Side = Literal["scene", "library"]

SAMPLING_TRACE = SphereTracerConfig(
    max_steps=128, omega=1.6, adaptive=True, grid_resolution=0, refine="bisection", max_refine=20,
    footprint_fraction=0.0, check_camera=False,
)
"""The tracer's settings for surface sampling: verified over-relaxed steps adapted to the
SDF's slope (the renderer's, see :mod:`regnf.render.sphere_tracer`), at most 128 steps a
ray, no empty-space grid (one trace per field and box: building a grid would cost more than it
saves), bisection of a crossing to an absolute tolerance of 1e-5 field units: a surface point,
not a pixel, is wanted. Faster than plain steps of a fraction of the SDF, with the same points
but for a few grazing rays (docs/decisions/surface-sampling.md)."""


@dataclass(frozen=True)
class SamplingConfig:
    """Settings of :func:`sample_surface`: distances relative to the proposal box, except
    ``trace`` (field units; its ``near`` and ``far`` are set per ray here)."""

    n_views: int = 5
    """Cameras (paper: 5 = +x, -x, +y, -y, top-down; <= 6 adds bottom-up; > 6: Fibonacci)."""
    views: Literal["multi", "single"] = "multi"
    """``single``: one camera along ``single_view_direction`` (the paper's Table II)."""
    single_view_direction: tuple[float, float, float] = (-1.0, 0.0, 0.15)
    """Box centre -> single camera, in the (x, y, up) basis: a low side view from -x."""
    single_view_zoom: float = 3.0
    """Narrows the single view's field of view by this factor (> 1: only part in frame; docs/decisions/surface-sampling.md)."""
    rays_per_side: int = 64
    """Rays along each image axis (paper: every 8th pixel of a 512 image)."""
    distance_factor: float = 2.5
    """Camera distance from the box centre in units of the inflated box's radius (> 1)."""
    fov_margin: float = 1.02
    """The field of view fits the inflated box's bounding sphere grown by this factor."""
    box_inflate: float = 0.1
    """Scene side: hits are kept inside the box with half extents grown by this fraction."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Up axis in the FIELD frame (scene fields: +Z, their to_world has no rotation)."""
    remove_floor: bool = True
    """Scene side: fit the supporting floor plane and drop the points on (or below) it."""
    floor_max_tilt_deg: float = 10.0
    """The floor's normal (and its candidate points' normals) lies within this of ``up``."""
    floor_band_rel: float = 0.05
    """Floor candidates lie within this fraction of the box height above the lowest hit."""
    floor_tol_rel: float = 0.01
    """Points less than this fraction of the inflated box's diagonal above the floor go."""
    floor_min_fraction: float = 0.01
    """A plane is a floor only if at least this fraction of the hits (and 10) are on it."""
    floor_ransac_iters: int = 200
    """Plane hypotheses tried by the floor RANSAC before the least-squares refit."""
    underside_deg: float = 60.0
    """Scene hits facing within this many degrees of down are dropped; 0 keeps them (docs/decisions/surface-sampling.md)."""
    surface_tol_rel: float = 1e-4
    """Hits with |sdf| above this fraction of the box diagonal go (rays started in matter, unconverged brackets)."""
    voxel_size_rel: float = 0.01
    """Downsampling voxel as a fraction of the box diagonal (0 disables)."""
    max_points: int = 5000
    """Cap on the returned points (paper: 5000); a seeded random subset beyond it."""
    seed: int = 0
    """Seed of the floor RANSAC and of the subsampling (the result is deterministic)."""
    trace: SphereTracerConfig = field(default_factory=lambda: SAMPLING_TRACE)
    """The sphere tracer's settings (:data:`SAMPLING_TRACE`)."""

    def __post_init__(self) -> None:
        if self.views not in ("multi", "single"):
            raise RegnfError(f"views must be 'multi' or 'single', got {self.views!r}")
        if self.n_views < 1 or self.rays_per_side < 1 or self.max_points < 1:
            raise RegnfError("n_views, rays_per_side and max_points must be >= 1")
        if not self.fov_margin >= 1.0 or not self.distance_factor > self.fov_margin:
            raise RegnfError(
                f"need distance_factor > fov_margin >= 1 (cameras outside the box's sphere), "
                f"got {self.distance_factor} and {self.fov_margin}"
            )
        if self.box_inflate <= -1 or self.voxel_size_rel < 0 or self.surface_tol_rel <= 0:
            raise RegnfError("box_inflate must be > -1, voxel_size_rel >= 0, surface_tol_rel > 0")
        if not 0.0 <= self.underside_deg < 90.0:
            raise RegnfError(f"underside_deg must be in [0, 90), got {self.underside_deg}")
        if self.single_view_zoom <= 0:
            raise RegnfError(f"single_view_zoom must be > 0, got {self.single_view_zoom}")
        for name in ("up", "single_view_direction"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) == 0:
                raise RegnfError(f"{name} must be a non-zero 3-vector, got {getattr(self, name)}")


class CameraRig(NamedTuple):
    """The virtual cameras of one sampling run (OpenCV axes, posed in the FIELD frame)."""

    camtoworld: np.ndarray
    """(v, 4, 4) float64: camera -> field frame."""
    K: np.ndarray
    """(3, 3) float64: intrinsics shared by all views."""
    size: int
    """Image width = height in pixels (one ray per pixel centre)."""


class SurfaceSamples(NamedTuple):
    """Surface points of one field around one proposal, in that FIELD's frame."""

    points: np.ndarray
    """(n, 3) float64."""
    normals: np.ndarray
    """(n, 3) float64: unit outward normals (normalised SDF gradient)."""
    view_ids: np.ndarray
    """(n,) int64: index of the camera whose ray found the point."""


class FloorPlane(NamedTuple):
    """A fitted floor ``{x : normal . x = offset}``."""

    normal: np.ndarray
    """(3,) unit, pointing up."""
    offset: float
    """``normal . x`` on the plane."""
    n_inliers: int
    """Hits within the tolerance of the plane."""


# -- cameras ---------------------------------------------------------------------------------
def _basis(up: np.ndarray) -> np.ndarray:
    """(3, 3) rows (e1, e2, up): a right-handed frame with ``e1`` as close to +x as possible."""
    u = up / np.linalg.norm(up)
    ref = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ u) * u
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1), u])


def view_directions(config: SamplingConfig) -> np.ndarray:
    """(v, 3) unit directions from the box centre to the cameras, in the (x, y, up) basis.

    ``n <= 6``: the first ``n`` of +x, -x, +y, -y, +up, -up; ``n > 6``: a Fibonacci lattice on
    the upper hemisphere including the equator (elevation in [0, 90] degrees).
    """
    if config.views == "single":
        d = np.asarray(config.single_view_direction, dtype=np.float64)
        return (d / np.linalg.norm(d))[None]
    n = config.n_views
    if n <= 6:
        return np.array(
            [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float
        )[:n]
    i = np.arange(n, dtype=np.float64)
    z = (i + 0.5) / n  # uniform in z over [0, 1]: uniform in area on the hemisphere
    phi = i * math.pi * (3.0 - math.sqrt(5.0))  # golden angle
    rho = np.sqrt(1.0 - z**2)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


def camera_rig(box: OrientedBox, config: SamplingConfig = SamplingConfig()) -> CameraRig:
    """Cameras around ``box`` (already inflated as wanted), looking at its centre.

    Each camera sits at ``distance_factor * box.radius`` from the centre, and the field of
    view is the smallest that contains the box's bounding sphere (times ``fov_margin``), so
    the whole setup scales with the box.
    """
    B = _basis(np.asarray(config.up, dtype=np.float64))
    dirs = view_directions(config) @ B  # (v, 3) in the field frame
    dist = config.distance_factor * box.radius
    eyes = box.center + dist * dirs
    fwd = -dirs
    # Image "up" is the field's up; a camera looking along it uses e1 instead.
    ref = np.where((np.abs(fwd @ B[2]) > 0.999)[:, None], B[0], B[2])
    right = np.cross(fwd, ref)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    C = np.tile(np.eye(4), (len(dirs), 1, 1))
    C[:, :3, 0], C[:, :3, 1], C[:, :3, 2], C[:, :3, 3] = right, down, fwd, eyes
    half = math.asin(config.fov_margin / config.distance_factor)
    if config.views == "single":
        half = math.atan(math.tan(half) / config.single_view_zoom)
    n = config.rays_per_side
    f = 0.5 * n / math.tan(half)
    K = np.array([[f, 0.0, 0.5 * n], [0.0, f, 0.5 * n], [0.0, 0.0, 1.0]])
    return CameraRig(C, K, n)


def _rig_rays(rig: CameraRig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """float64 CPU origins (m, 3), directions (m, 3) and view ids (m,) of all cameras."""
    rays = [pinhole_rays(rig.K, C, rig.size, rig.size, dtype=torch.float64) for C in rig.camtoworld]
    o = torch.cat([r[0] for r in rays])
    d = torch.cat([r[1] for r in rays])
    ids = torch.arange(len(rays)).repeat_interleave(rig.size * rig.size)
    return o, d, ids


# -- floor -----------------------------------------------------------------------------------
def fit_floor(
    points: np.ndarray,
    normals: np.ndarray,
    box: OrientedBox,
    config: SamplingConfig = SamplingConfig(),
) -> FloorPlane | None:
    """Fit the supporting floor among the lowest upward-facing hits, or ``None`` if there is none.

    RANSAC over plane hypotheses through 3 candidates (tilt within ``floor_max_tilt_deg`` of
    ``up``), then a least-squares refit on the inliers. Candidates are hits whose normal is
    within the tilt of ``up`` and whose height is within ``floor_band_rel`` of the box height
    above the lowest hit.

    Parameters
    ----------
    points, normals : (n, 3) float
        Hits and unit normals in the field frame.
    box : OrientedBox
        The proposal (sets the tolerances).
    config : SamplingConfig

    Returns
    -------
    FloorPlane or None
    """
    up = np.asarray(config.up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    n = len(points)
    cos_tilt = math.cos(math.radians(config.floor_max_tilt_deg))
    min_inliers = max(10, math.ceil(config.floor_min_fraction * n))
    if n < min_inliers:
        return None
    tol = config.floor_tol_rel * box.diagonal
    height = points @ up
    box_height = 2.0 * float(np.abs(box.rotation.T @ up) @ box.half_extents)
    cand = (normals @ up >= cos_tilt) & (
        height <= height.min() + config.floor_band_rel * box_height
    )
    P = points[cand]
    if len(P) < min_inliers:
        return None
    rng = np.random.default_rng(config.seed)
    tri = P[rng.integers(0, len(P), size=(config.floor_ransac_iters, 3))]  # (k, 3, 3)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(nrm, axis=1)
    ok = length > 1e-12 * box.diagonal**2
    nrm = nrm[ok] / length[ok, None]
    nrm *= np.sign(nrm @ up)[:, None]
    ok2 = nrm @ up >= cos_tilt
    nrm, p0 = nrm[ok2], tri[ok][ok2, 0]
    if len(nrm) == 0:
        return None
    dist = np.abs(P @ nrm.T - np.einsum("kj,kj->k", nrm, p0))  # (m, k)
    best = int(np.argmax((dist < tol).sum(axis=0)))
    inl = P[dist[:, best] < tol]
    # Least-squares refit: the plane through the inliers' centroid, normal = least spread.
    c = inl.mean(axis=0)
    normal = np.linalg.svd(inl - c, full_matrices=False)[2][-1]
    normal = normal * (1.0 if normal @ up >= 0 else -1.0)
    if normal @ up < cos_tilt:
        return None
    offset = float(normal @ c)
    n_in = int((np.abs(points @ normal - offset) < tol).sum())
    if n_in < min_inliers:
        return None
    return FloorPlane(normal, offset, n_in)


# -- sampling --------------------------------------------------------------------------------
def _finite_check(field: Field, values: torch.Tensor, what: str) -> None:
    bad = ~torch.isfinite(values)
    if bad.ndim > 1:
        bad = bad.any(dim=-1)
    if bool(bad.any()):
        name = field.name or type(field).__name__
        raise RegnfError(
            f"field {name!r} returned non-finite values ({what}) at {int(bad.sum())} of "
            f"{bad.numel()} points around the proposal box; the field (checkpoint) is broken"
        )


def _sdf_and_grad(field: Field, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # A loop over chunks (not points) bounds the autograd memory of big batches.
    parts = [
        field.sdf_and_gradient(x[i : i + DEFAULT_CHUNK]) for i in range(0, len(x), DEFAULT_CHUNK)
    ]
    if not parts:
        return x.new_zeros(0), x.new_zeros(0, 3)
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def _voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices (sorted) of one point per occupied voxel: the one closest to the voxel centre."""
    if voxel <= 0 or len(points) == 0:
        return np.arange(len(points))
    q = (points - points.min(axis=0)) / voxel
    keys = np.floor(q).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    off = np.linalg.norm(q - keys - 0.5, axis=1)
    order = np.lexsort((np.arange(len(points)), off, inv))  # by voxel, then closeness
    first = np.ones(len(order), dtype=bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return np.sort(order[first])


@torch.no_grad()
def sample_surface(
    field: Field,
    box: OrientedBox | None = None,
    config: SamplingConfig = SamplingConfig(),
    side: Side = "scene",
    device: torch.device | str | None = None,
) -> SurfaceSamples:
    """Surface points and normals of ``field`` seen by virtual cameras around ``box``.

    Parameters
    ----------
    field : Field
        Any field (neural, analytic, composite).
    box : OrientedBox, optional
        The proposal in the FIELD frame; required on the scene side, the field's bounds by
        default on the library side.
    config : SamplingConfig
    side : {"scene", "library"}
        Scene: rays start at the inflated box, hits outside it and the floor are dropped.
        Library: all hits are kept.
    device : torch.device or str, optional
        Where the field is evaluated; the field's device by default (the field is not moved).

    Returns
    -------
    SurfaceSamples
        float64 numpy arrays in the field frame, at most ``config.max_points`` points.

    Raises
    ------
    ValueError
        For an unknown ``side``, a missing scene box, a field that returns non-finite values,
        or no surface left (the proposal box contains no surface).
    """
    if side not in ("scene", "library"):
        raise RegnfError(f"side must be 'scene' or 'library', got {side!r}")
    if box is None:
        if side == "scene":
            raise RegnfError("the scene side needs a proposal box (the object's box in the field)")
        lo, hi = field.bounds.detach().cpu().double().numpy()
        box = OrientedBox.from_aabb(lo, hi)
    dev = field.device
    if device is not None and not _same_device(torch.device(device), dev):
        raise RegnfError(f"field is on {dev}, not on the requested device {device}; move it first")
    dtype = field.bounds.dtype
    big = box.inflated(config.box_inflate)
    o, d, ids = _rig_rays(camera_rig(big, config))

    # Start each ray where it enters the inflated box (box-local slab test, float64).
    R = torch.as_tensor(big.rotation)
    ol = (o - torch.as_tensor(big.center)) @ R
    h = torch.as_tensor(big.half_extents)
    t_in, t_out = ray_aabb(ol, d @ R, -h, h)
    through = t_out >= t_in.clamp(min=0.0)
    o, d, ids, t_in, t_out = o[through], d[through], ids[through], t_in[through], t_out[through]
    if side == "scene":
        o = o + t_in.clamp(min=0.0)[:, None] * d
        far = float((t_out - t_in.clamp(min=0.0)).max()) * 1.001 if len(o) else 1.0
    else:
        far = math.inf
    # Probe where the rays enter the box: a broken (NaN) field is an error, not a "miss".
    entry = o if side == "scene" else o + t_in.clamp(min=0.0)[:, None] * d
    if len(entry):
        _finite_check(field, field.sdf_chunked(entry.to(device=dev, dtype=dtype)), "SDF")

    # The tracer takes its range in metres (a user's unit); ``far`` is in field units here.
    tracer = dataclasses.replace(config.trace, near=0.0, far=far * field.world_scale)
    tr = trace(field, o.to(device=dev, dtype=dtype), d.to(device=dev, dtype=dtype), tracer)
    hit = tr.hit.cpu()
    pts = tr.points[tr.hit.to(tr.points.device)]
    ids = ids[hit]
    sdf, grad = _sdf_and_grad(field, pts)
    _finite_check(field, sdf, "SDF at surface hits")
    _finite_check(field, grad, "SDF gradient at surface hits")
    gnorm = torch.linalg.vector_norm(grad, dim=-1)
    keep = (sdf.abs() <= config.surface_tol_rel * box.diagonal) & (gnorm > 1e-12)
    P = pts[keep].double().cpu().numpy()
    N = (grad[keep] / gnorm[keep, None]).double().cpu().numpy()
    V = ids[keep.cpu()].numpy().astype(np.int64)

    if side == "scene":
        inside = big.contains(P, pad_rel=1e-6)
        P, N, V = P[inside], N[inside], V[inside]
        if len(P) == 0:
            raise RegnfError(_empty_message(field, "no ray hit any surface inside it"))
        if config.remove_floor:
            plane = fit_floor(P, N, big, config)
            if plane is not None:
                above = P @ plane.normal - plane.offset >= config.floor_tol_rel * big.diagonal
                P, N, V = P[above], N[above], V[above]
                if len(P) == 0:
                    raise RegnfError(_empty_message(field, "only the floor was found"))
        if config.underside_deg > 0:
            up = np.asarray(config.up, dtype=np.float64)
            facing = N @ (up / np.linalg.norm(up)) > -math.cos(math.radians(config.underside_deg))
            # Where every hit faces down (a box under a ceiling or a shelf), they are all the
            # evidence there is: kept.
            if facing.any():
                P, N, V = P[facing], N[facing], V[facing]
    elif len(P) == 0:
        raise RegnfError(
            f"library field {field.name or type(field).__name__!r}: no ray hit its surface "
            "(the proposal box contains no surface)"
        )

    sel = _voxel_downsample(P, config.voxel_size_rel * box.diagonal)
    if len(sel) > config.max_points:
        rng = np.random.default_rng(config.seed)
        sel = np.sort(rng.choice(sel, size=config.max_points, replace=False))
    return SurfaceSamples(P[sel], N[sel], V[sel])


def _same_device(a: torch.device, b: torch.device) -> bool:
    """Whether two devices are one (an index-less device means the backend's current one)."""
    if a.type != b.type:
        return False
    if a.index is None and b.index is None or a.index == b.index:
        return True
    module = getattr(torch, a.type, None)  # e.g. torch.cuda for accelerators
    current = module.current_device() if module is not None and hasattr(module, "current_device") else 0
    return (a.index if a.index is not None else current) == (b.index if b.index is not None else current)


def _empty_message(field: Field, why: str) -> str:
    name = field.name or type(field).__name__
    return (
        f"scene field {name!r}: the proposal box contains no surface ({why}); check that the "
        "box is in the scene FIELD frame (use OrientedBox.transformed(inverse(to_world)) for a "
        "box in metres)"
    )
