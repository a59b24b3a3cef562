"""Train a neural SDF from posed RGB-D images (depth-supervised, NeuS-style in spirit).

Losses, each in units of the finest grid cell so that their weights mean the same thing at
every scale:

- surface: |S(x)| at back-projected depth points;
- near-surface: S(x + e n) = e for small offsets e along the depth-derived normal n;
- free space: S >= 0 in front of every observed surface and along rays that hit nothing,
  and S <= the remaining ray distance (the hit is that far along the ray; for noisy depth, that
  far plus ``free_sigma_multiple`` x its sigma); uniform points
  that a random training view sees as empty (in front of its depth, or on a ray that hit
  nothing) must be positive too, which carves floaters out of rarely seen corners;
- occluding edges (``w_edge > 0``): S >= 0 on the rays that pass just beside an observed
  silhouette, near the occluder's depth, which pins the outline of thin parts;
- outlines (``w_outline > 0``): |S| at the occluders' own points along those silhouettes, the
  few pixels that see a surface at a grazing angle: the surface's side of the same outline;
- floater pool (``carve_every > 0``): S >= 0 at points found inside the field where a training
  view saw free space, kept until training has carved them
  (:mod:`regnf.training.floater_pool`);
- eikonal: |grad S| = 1 (finite differences: grid_sample has no second derivative), at
  surface samples only. Applied at sparse uniform points it moves fine-grid cells that are
  touched once in a while, and Adam turns any such tiny gradient into a full-size step:
  that left ~30 one-voxel floaters in free space per object; surface-only leaves none;
- normals: grad S parallel to the depth-derived normal;
- colour: L1 between the colour head at surface points and the observed pixel;
- optionally (``w_volume_color > 0``), NeuS volume rendering: L1 between the colour
  volume-rendered along a training ray (near its observed depth) and the pixel.

Depth with a noise model (:attr:`regnf.captures.model.Capture.depth_noise`, every capture but
regnf's ideal renders) is trusted by how noisy it is: the surface, near-surface, normal and colour
terms are means weighted by each sample's ``RGBDSamples.weights``, and free space (the samples on
observed rays and what a view sees free) stops ``max(free_margin_m, free_sigma_multiple x
sigma)`` before the depth (:func:`free_stop`), and the bound on S from the remaining ray distance
reaches as far beyond it. Exact depth keeps the unweighted means, the fixed margin and the
bound at the depth, bit for bit.

Where the capture's poses are estimates (``RGBDTrainConfig.pose_refine``), each training frame's
pose gets a small rigid correction trained with the field: from ``pose_refine.start`` on, every
sample a frame saw moves with its frame (:mod:`regnf.training.pose_refinement`), and the
corrections applied are in ``TrainLog.pose_refinement`` and the field's provenance. Exact poses
train as they always did.

The trained field records where its training views observed space: ``field.visibility``,
a :class:`regnf.observations.visibility.VisibilityGrid` over its bounds (see
``RGBDTrainConfig.visibility_resolution``), saved with it by :mod:`regnf.io.checkpoint`.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from regnf.captures.depth_uncertainty import DepthNoiseModel
from regnf.captures.model import CaptureError
from regnf.core.errors import RegnfError
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import (
    NeuralSDF,
    NeuralSDFConfig,
    tetrahedral_combine,
    tetrahedral_points,
)
from regnf.observations.rgbd_samples import (
    CaptureLike,
    RGBDSamples,
    build_samples,
    capture_where,
    measured_depth,
    ray_box_interval,
)
from regnf.observations.view_lenses import ViewLenses
from regnf.observations.visibility import DEFAULT_MARGIN, DEFAULT_RESOLUTION, build_visibility
from regnf.training.floater_pool import FloaterPool
from regnf.training.optim import OptimiserConfig, finest_voxel, optimise
from regnf.training.pose_refinement import PoseCorrections, PoseRefineConfig, PoseReport
from regnf.training.volume_render import render_rays_neus

NOISY_DEPTH_VERSION = 4
"""Version of what training makes of depth with a noise model: part of the cache key of the
fields trained on such depth only (an exact-depth field keeps its key), raised when the code
changes it."""

TRAIN_VERSION = 2
"""Version of what a field trained on given captures with a given config is (part of cache
keys; bump it when a default changes what training makes). 2: the learning rates decay to
``lr_final`` = 0.01 of their start, not 0.1."""


@dataclass
class RGBDTrainConfig(OptimiserConfig):
    """How to train a field from RGB-D frames (the optimiser's settings: :class:`OptimiserConfig`)."""

    batch_surface: int = 4096
    """Surface points (and as many near-surface points) per step."""
    batch_free: int = 2048
    """Free-space samples per step, on rays that hit a surface."""
    batch_empty: int = 2048
    """Free-space samples per step, on rays that hit nothing."""
    batch_eikonal: int = 1024
    """Uniform points in the bounds for the eikonal loss per step."""
    near_band_m: tuple[float, float] = (0.006, 0.02)
    """Near-surface offsets, metres: up to this far inside and outside (thin parts >= 1.2 cm)."""
    free_margin_m: float = 0.02
    """Free-space samples stop this many metres before the observed surface (at least; see ``free_sigma_multiple``)."""
    free_sigma_multiple: float = 3.0
    """Free space stops max(free_margin_m, this x the pixel's depth sigma) before the observed surface (depth with a noise model; docs/decisions/depth-weights.md)."""
    pixel_stride: int = 1
    """Sample every this-many-th pixel in u and v of each training frame (:func:`regnf.observations.rgbd_samples.build_samples`)."""
    w_surface: float = 1.0
    """Weight of the surface loss."""
    w_near: float = 1.0
    """Weight of the near-surface loss."""
    w_free: float = 1.0
    """Weight of the free-space loss."""
    w_edge: float = 0.0
    """Weight of the occluding-edge loss, 0 for off (docs/decisions/room-training-losses.md)."""
    batch_edge: int = 2048
    """Samples per step on the rays that pass an occluding edge."""
    edge_band_m: tuple[float, float] = (0.02, 0.05)
    """Edge samples' span before and after the occluder's depth, metres (never within free_margin_m of the hit)."""
    w_outline: float = 0.0
    """Weight of the outline loss, 0 for off (docs/decisions/room-training-losses.md)."""
    batch_outline: int = 1024
    """Outline points per step (drawn with replacement)."""
    carve_every: int = 0
    """Steps between the floater pool's mining passes, 0 for no pool (docs/decisions/room-training-losses.md)."""
    carve_from: float = 0.5
    """When the first mining pass runs and the pool's loss starts, fraction of the steps."""
    carve_spacing_m: float = 0.04
    """Grid spacing of a mining pass, metres (random offset each pass; pool points move by up to half)."""
    batch_carve: int = 512
    """Pool points per step."""
    w_eikonal: float = 0.1
    """Weight of the eikonal loss."""
    w_normal: float = 0.05
    """Weight of the normal loss."""
    w_color: float = 1.0
    """Weight of the colour loss."""
    w_volume_color: float = 0.0
    """Weight of the optional NeuS volume-rendering colour loss (0: off)."""
    volume_rays: int = 256
    """Rays per step for the volume-rendering colour loss."""
    volume_samples: int = 32
    """Samples per ray, within +-volume_band_m of the observed depth."""
    volume_band_m: float = 0.05
    """Half-width of the rendered interval around the observed surface, metres."""
    volume_inv_s: float = 400.0
    """NeuS sharpness s (in 1/field units): the logistic density's inverse width."""
    bounds_margin: float = 0.08
    """Field bounds: the observed points' box grown by this fraction of its size per side."""
    seed: int = 0
    """Seed of the sampling and the initialisation."""
    device: str = "cpu"
    """Torch device to train on."""
    visibility_resolution: int = DEFAULT_RESOLUTION
    """Voxels along the longest axis of the visibility grid, 0 for none (docs/decisions/field-training.md)."""
    visibility_margin: float = DEFAULT_MARGIN
    """Voxels behind each observed surface that the visibility grid counts as observed."""
    architecture: NeuralSDFConfig = field(default_factory=NeuralSDFConfig)
    """Architecture of the field."""
    pose_refine: PoseRefineConfig = field(default_factory=PoseRefineConfig)
    """Joint refinement of the training poses, by default of estimated ones (docs/decisions/pose_refinement.md)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        name = type(self).__name__
        non_negative = ("w_surface", "w_near", "w_free", "w_edge", "w_outline", "w_eikonal", "w_normal", "w_color",
                        "w_volume_color", "free_margin_m", "free_sigma_multiple", "bounds_margin", "visibility_margin")
        for key in non_negative:
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) >= 0):
                raise RegnfError(f"{name}.{key} must be a finite number >= 0, got {getattr(self, key)}")
        counts = ("batch_surface", "batch_free", "batch_empty", "batch_eikonal", "batch_edge", "batch_outline",
                  "batch_carve", "carve_every", "volume_rays", "volume_samples", "visibility_resolution")
        for key in (*counts, "pixel_stride"):
            at_least = 1 if key == "pixel_stride" else 0
            value = getattr(self, key)
            if isinstance(value, bool) or int(value) != value or value < at_least:
                raise RegnfError(f"{name}.{key} must be a whole number >= {at_least}, got {value}")
        if not 0.0 <= self.carve_from <= 1.0:
            raise RegnfError(f"{name}.carve_from is a fraction of the steps, in [0, 1]; got {self.carve_from}")
        for key in ("carve_spacing_m", "volume_band_m", "volume_inv_s"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) > 0):
                raise RegnfError(f"{name}.{key} must be finite and > 0, got {getattr(self, key)}")


@dataclass
class TrainLog:
    """What happened during training."""

    seconds: float = 0.0
    steps: int = 0
    losses: list[dict] = field(default_factory=list)
    pose_refinement: PoseReport | None = None
    """The size of the pose corrections applied (None: refinement off)."""
    corrected_poses: np.ndarray | None = None
    """(n, 4, 4) float64 corrected camtoworld of the training frames in order, normalised frame (None: off)."""


class _ViewStack:
    """Depth images of the training views on the device, for projective free-space tests."""

    noise: DepthNoiseModel | None = None
    """The capture's depth noise model (None: exact depth, the margin as given)."""
    scale: float = 1.0
    """Metres per normalised unit of the capture."""
    sigma_multiple: float = 3.0
    """Free space stops max(margin, this x the pixel's depth sigma) before its depth."""

    def __init__(self, depth: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                 lenses: ViewLenses | None = None) -> None:
        self.depth, self.K, self.w2c, self.lenses = depth, K, w2c, lenses
        self.count = depth.shape[0]

    @staticmethod
    def build(capture: CaptureLike, indices: Sequence[int], device: torch.device,
              sigma_multiple: float = 3.0) -> _ViewStack:
        """The stack of frames ``indices``; ``sigma_multiple``: see :attr:`sigma_multiple`."""
        depth = np.stack([measured_depth(capture, i, free=True) for i in indices]).astype(np.float32)
        if not capture.zero_depth_is_empty:
            # NaN fails both tests of seen_free: a pixel of unknown depth sees nothing free.
            depth = np.where(depth > 0, depth, np.float32(np.nan))
        K = np.stack([np.asarray(capture.frames[i].intrinsics, np.float64) for i in indices])
        c2w = np.stack([np.asarray(capture.frames[i].camtoworld, np.float64) for i in indices])
        w2c = np.linalg.inv(c2w)
        distortions = [capture.frames[i].distortion for i in indices]
        stack = _ViewStack(
            torch.from_numpy(depth).to(device),
            torch.from_numpy(K).float().to(device),
            torch.from_numpy(w2c).float().to(device),
            ViewLenses.build(distortions, K, depth.shape[2], depth.shape[1], device),
        )
        stack.noise, stack.scale, stack.sigma_multiple = capture.depth_noise, float(capture.scale), sigma_multiple
        return stack

    def pixel_of(self, x: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel coordinates ``(u, v)`` and z-depth ``z`` (n,) of points ``x`` (n, 3) in views ``view`` (n,).

        Through each view's lens where the stack has distortion (``u = v = -1`` for a point
        beyond the radius holding its image); a view without distortion is a pinhole.
        """
        R, t, K = self.w2c[view, :3, :3], self.w2c[view, :3, 3], self.K[view]
        pc = (R @ x[:, :, None]).squeeze(-1) + t
        z = pc[:, 2]
        zs = z.clamp_min(1e-6)
        u = K[:, 0, 0] * pc[:, 0] / zs + K[:, 0, 2]
        v = K[:, 1, 1] * pc[:, 1] / zs + K[:, 1, 2]
        if self.lenses is not None:
            ud, vd, distorted = self.lenses.pixels(pc[:, :2] / zs[:, None], view, K)
            u, v = torch.where(distorted, ud, u), torch.where(distorted, vd, v)
        return u, v, z

    def seen_free(self, x: torch.Tensor, margin: float, view: torch.Tensor) -> torch.Tensor:
        """(n,) float: 1 where view ``view[i]`` sees point ``x[i]`` in front of its surface.

        A pixel with depth 0 sees its whole ray free; one with NaN (unknown) sees nothing.
        """
        u, v, z = self.pixel_of(x, view)
        h, w = self.depth.shape[1:]
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui = u.clamp(0, w - 1).long()
        vi = v.clamp(0, h - 1).long()
        d = self.depth[view, vi, ui]
        # The depth's sigma at normal incidence (the stack keeps no normals), in normalised units.
        sigma = None if self.noise is None else self.noise.sigma_normal(d * self.scale) / self.scale
        free = inside & ((d <= 0) | (z < free_stop(d, sigma, margin, self.sigma_multiple)))
        return free.float()


_POOL_CAPACITY = 1 << 16
"""Points the floater pool keeps (a mining pass over a room adds a few thousand)."""

def free_stop(t: torch.Tensor, sigma: torch.Tensor | None, margin: float, multiple: float) -> torch.Tensor:
    """Where free space in front of an observed depth ``t`` (n,) stops: ``t - max(margin, multiple * sigma)``.

    ``sigma`` (n,) is the depth's noise in the same unit; None (exact depth): ``t - margin``.
    """
    return t - (margin if sigma is None else torch.clamp_min(multiple * sigma, margin))


def hit_reach(t: torch.Tensor, sigma: torch.Tensor | None, multiple: float) -> torch.Tensor:
    """How far along its ray an observed depth ``t`` (n,) puts the hit at most: ``t + multiple * sigma``.

    The free-space term keeps S below the remaining distance to it. Noisy depth lies short of
    the surface by up to a few sigma; a bound at the depth itself would pull the surface toward
    the camera by the noise. ``sigma`` (n,) in the unit of ``t``; None (exact depth): ``t``.
    """
    return t if sigma is None else t + multiple * sigma


def _weighted_mean(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """sum(w x) / sum(w) of per-sample terms ``x`` (n,) and weights ``w`` (n,) > 0."""
    return (x * w).sum() / w.sum()


def fit_bounds(samples: RGBDSamples, margin: float, limit: torch.Tensor | None) -> torch.Tensor:
    """(2, 3) bounds around the observed points, grown by ``margin`` of the extent per side."""
    lo = samples.points.min(0).values
    hi = samples.points.max(0).values
    pad = (hi - lo).max() * margin
    lo, hi = lo - pad, hi + pad
    if limit is not None:
        lo, hi = torch.maximum(lo, limit[0]), torch.minimum(hi, limit[1])
    return torch.stack([lo, hi])


def train_rgbd(
    capture: CaptureLike,
    config: RGBDTrainConfig | None = None,
    info: FieldInfo | None = None,
    indices: Sequence[int] | None = None,
    progress: bool = True,
) -> tuple[NeuralSDF, TrainLog]:
    """Train a :class:`NeuralSDF` on the training frames of ``capture``.

    The field lives in the capture's normalised frame; its ``to_world`` is the capture's
    ``worldtogt``. Deterministic on CPU for a given seed. Unless
    ``config.visibility_resolution`` is 0, the field carries the visibility grid of the frames
    it trained on (``field.visibility``, over ``field.bounds``).

    Every training frame is read (and its image and depth checked) before the first step.

    Raises
    ------
    CaptureError
        No training frame, a frame without depth, an unreadable or invalid image or depth
        (naming the file and the frame), or too few valid depth pixels.
    """
    cfg = config or RGBDTrainConfig()
    t_start = time.perf_counter()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    device = torch.device(cfg.device)
    if indices is None:
        indices = capture.train_indices()
    if len(indices) == 0:
        raise CaptureError(f"{capture_where(capture)}: the capture has no training frames")
    samples = build_samples(capture, indices, cfg.pixel_stride)
    if samples.points.shape[0] < 100:
        raise CaptureError(
            f"{capture_where(capture)}: only {samples.points.shape[0]} valid depth pixels in "
            f"{len(indices)} training frames: nothing to train on"
        )
    aabb = getattr(capture, "scene_box", {}).get("aabb") if hasattr(capture, "scene_box") else None
    limit = torch.as_tensor(np.asarray(aabb), dtype=torch.float32) if aabb is not None else None
    bounds = fit_bounds(samples, cfg.bounds_margin, limit)
    to_world = torch.as_tensor(np.asarray(capture.worldtogt), dtype=torch.float64)
    info = info or FieldInfo()
    model = NeuralSDF(cfg.architecture, bounds=bounds, to_world=to_world, info=info).to(device)
    scale = model.world_scale
    ell = finest_voxel(model)
    h_fd = 0.5 * ell
    band_in, band_out = cfg.near_band_m[0] / scale, cfg.near_band_m[1] / scale
    margin = cfg.free_margin_m / scale

    s = RGBDSamples(*(None if t is None else t.to(device) for t in samples))
    views = _ViewStack.build(capture, indices, device, cfg.free_sigma_multiple)
    # Depth with a noise model: its samples are weighted and free space keeps off its sigma;
    # exact depth keeps the unweighted arithmetic.
    weighted = capture.depth_noise is not None
    ok_idx = torch.nonzero(s.normal_ok).squeeze(1)
    if ok_idx.numel() == 0:
        raise RegnfError("no depth pixel has a reliable normal; is the depth image constant?")
    m, k = s.points.shape[0], s.free_origins.shape[0]
    n_edge = s.edge_t.shape[0] if cfg.w_edge > 0 else 0
    outline_idx = torch.nonzero(s.outline).squeeze(1) if cfg.w_outline > 0 else s.outline[:0].long()
    n_outline = cfg.batch_outline if outline_idx.numel() > 0 else 0
    edge_before, edge_after = cfg.edge_band_m[0] / scale, cfg.edge_band_m[1] / scale
    bounds_d = model.bounds
    log = TrainLog()
    # The grid of what the training views observed: attached to the field, and where the
    # floater pool's mining passes look (nothing is asked of space no view saw).
    visibility = build_visibility(
        capture, model.bounds, resolution=cfg.visibility_resolution,
        margin=cfg.visibility_margin, device=device, indices=indices,
    ) if cfg.visibility_resolution > 0 else None
    pool = FloaterPool(_POOL_CAPACITY, device) if cfg.carve_every > 0 else None
    # Pose corrections move the samples of each frame. The view stack and the visibility grid keep
    # the poses as given: a view's free-space test takes the point back to where that view saw
    # it, and the grid only says where anything was observed.
    poses = PoseCorrections(
        torch.from_numpy(np.stack([np.asarray(capture.frames[i].camtoworld, np.float64) for i in indices])),
        scale, cfg.pose_refine,
    ).to(device) if cfg.pose_refine.enabled(getattr(capture, "poses_estimated", False)) else None
    refine_start = int(cfg.pose_refine.start * cfg.steps)
    carve_start = int(cfg.carve_from * cfg.steps)
    carve_spacing = cfg.carve_spacing_m / scale

    def rand(n: int) -> torch.Tensor:
        return torch.rand(n, generator=gen).to(device)

    def randint(high: int, n: int) -> torch.Tensor:
        return torch.randint(high, (n,), generator=gen).to(device)

    def loss_at(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        # Every sample seen by a frame moves with that frame's pose correction, once it applies;
        # a view's free-space test takes the point back to where the view saw it as given.
        maps = poses.world_maps() if poses is not None and step >= refine_start else None

        def moved(x: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
            return x if maps is None else poses.points(x, frame, maps)

        def seen_free(x: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
            if maps is not None:
                with torch.no_grad():
                    x = poses.points_back(x, view, maps)
            return views.seen_free(x, margin, view)

        carving = pool is not None and step >= carve_start
        if carving and (step - carve_start) % cfg.carve_every == 0:
            pool.mine(model.sdf, bounds_d, carve_spacing, rand(3) * carve_spacing, seen_free,
                      views.count, visibility.observed if visibility is not None else None)
        # -- draw the batch -----------------------------------------------------------------

        ns = cfg.batch_surface
        si = ok_idx[randint(ok_idx.numel(), ns)]
        xs, nrm, col = moved(s.points[si], s.frame[si]), s.normals[si], s.colors[si]
        if maps is not None:
            nrm = poses.directions(nrm, s.frame[si], maps)
        # Surface points without a trusted normal still pin the zero level set.
        sa = randint(m, ns)
        xs_all = moved(s.points[sa], s.frame[sa])
        e = rand(ns) * (band_in + band_out) - band_in
        xn = xs + e[:, None] * nrm

        fi = randint(m, cfg.batch_free)
        o, p, td = s.origins[fi], s.points[fi], s.ray_t[fi]
        t_free = td if s.ray_free_t is None else s.ray_free_t[fi]
        d = (p - o) / td[:, None]
        t_in, _ = ray_box_interval(o, d, bounds_d)
        t_hi = free_stop(t_free, s.sigma[fi] if weighted else None, margin, cfg.free_sigma_multiple)
        t = t_in + rand(cfg.batch_free) * (t_hi - t_in).clamp_min(0.0)
        reach = hit_reach(td, s.sigma[fi] if weighted else None, cfg.free_sigma_multiple)
        xf, ub = moved(o + t[:, None] * d, s.frame[fi]), reach - t
        keep_f = (t_hi > t_in).float()

        if k > 0 and cfg.batch_empty > 0:
            ei = randint(k, cfg.batch_empty)
            eo, ed = s.free_origins[ei], s.free_dirs[ei]
            t0, t1 = ray_box_interval(eo, ed, bounds_d)
            te = t0 + rand(cfg.batch_empty) * (t1 - t0).clamp_min(0.0)
            xe_free = moved(eo + te[:, None] * ed, s.free_frame[ei])
            keep_e = (t1 > t0).float()
        else:
            xe_free = torch.zeros(0, 3, device=device)
            keep_e = torch.zeros(0, device=device)

        if n_edge > 0:
            gi = randint(n_edge, cfg.batch_edge)
            go, gd, gt = s.edge_origins[gi], s.edge_dirs[gi], s.edge_t[gi]
            g0, g1 = ray_box_interval(go, gd, bounds_d)
            lo = torch.maximum(gt - edge_before, g0)
            hi = torch.minimum(torch.minimum(gt + edge_after, s.edge_limit[gi] - margin), g1)
            xg = go + (lo + rand(cfg.batch_edge) * (hi - lo).clamp_min(0.0))[:, None] * gd
            xg = moved(xg, s.edge_frame[gi])
            keep_g = (hi > lo).float()
        else:
            xg = torch.zeros(0, 3, device=device)
            keep_g = torch.zeros(0, device=device)

        if n_outline:
            oi = outline_idx[randint(outline_idx.numel(), n_outline)]
            xo = moved(s.points[oi], s.frame[oi])
        else:
            xo = xs[:0]

        xu = bounds_d[0] + rand(cfg.batch_eikonal * 3).view(-1, 3) * (bounds_d[1] - bounds_d[0])
        if carving and len(pool) > 0:
            xc, vc = pool.draw(cfg.batch_carve, 0.5 * carve_spacing, rand, randint)
        else:
            xc, vc = xs[:0], ok_idx[:0]

        # -- one batched forward pass over every sample --------------------------------------
        # The eikonal loss is taken at the surface samples only, so the uniform points need no
        # gradient: one evaluation each for their free-space loss.
        fd_pts = tetrahedral_points(xs, h_fd)
        direct = torch.cat([xs, xs_all, xn, xf, xe_free, xg, xo, xc, xu])
        sdf_all, feat_all = model.sdf_and_features(torch.cat([direct, fd_pts]))
        sizes = [ns, ns, ns, xf.shape[0], xe_free.shape[0], xg.shape[0], xo.shape[0], xc.shape[0], xu.shape[0]]
        f_s, f_sa, f_n, f_f, f_e, f_g, f_o, f_c, f_u = torch.split(sdf_all[: direct.shape[0]], sizes)
        feat_s = feat_all[:ns]
        grads, _ = tetrahedral_combine(sdf_all[direct.shape[0]:], h_fd)
        g_s = grads[:ns]

        if weighted:
            w_s = s.weights[si]
            loss_surface = (_weighted_mean(f_s.abs(), w_s) + _weighted_mean(f_sa.abs(), s.weights[sa])) * 0.5 / ell
            loss_near = _weighted_mean((f_n - e).abs(), w_s) / ell
        else:
            loss_surface = (f_s.abs().mean() + f_sa.abs().mean()) * 0.5 / ell
            loss_near = (f_n - e).abs().mean() / ell
        free_terms = (F.relu(-f_f) + F.relu(f_f - ub)) * keep_f
        loss_free = free_terms.mean() / ell
        if f_e.numel():
            loss_free = loss_free + (F.relu(-f_e) * keep_e).mean() / ell
        gnorm = grads.norm(dim=-1)
        loss_eik = ((gnorm[:ns] - 1.0) ** 2).mean()
        # Uniform points seen as empty by a random view must not be inside anything.
        view_u = randint(views.count, xu.shape[0])
        free_u = seen_free(xu, view_u)
        loss_free = loss_free + (F.relu(-f_u) * free_u).mean() / ell
        if carving:
            found = (f_u.detach().reshape(-1) < 0) & (free_u > 0)
            pool.add(xu[found], view_u[found])
        if xc.shape[0]:
            loss_free = loss_free + (F.relu(-f_c) * seen_free(xc, vc)).mean() / ell
        loss_edge = (F.relu(-f_g) * keep_g).mean() / ell if n_edge > 0 else torch.zeros((), device=device)
        rgb = model.color_from(feat_s, F.normalize(g_s.detach(), dim=-1), None)
        if weighted:
            loss_normal = _weighted_mean(1.0 - F.cosine_similarity(g_s, nrm, dim=-1), w_s)
            loss_color = _weighted_mean((rgb - col).abs().mean(-1), w_s)
        else:
            loss_normal = (1.0 - F.cosine_similarity(g_s, nrm, dim=-1)).mean()
            loss_color = (rgb - col).abs().mean()
        loss = (
            cfg.w_surface * loss_surface + cfg.w_near * loss_near + cfg.w_free * loss_free
            + cfg.w_eikonal * loss_eik + cfg.w_normal * loss_normal + cfg.w_color * loss_color
        )
        if n_edge > 0:
            loss = loss + cfg.w_edge * loss_edge
        loss_outline = f_o.abs().mean() / ell if n_outline else torch.zeros((), device=device)
        if n_outline:
            loss = loss + cfg.w_outline * loss_outline
        loss_volume = torch.zeros((), device=device)
        if cfg.w_volume_color > 0:
            vi = randint(m, cfg.volume_rays)
            vo, vp, vt = s.origins[vi], s.points[vi], s.ray_t[vi]
            vd = (vp - vo) / vt[:, None]
            if maps is not None:
                vo, vd = poses.rays(vo, vd, s.frame[vi], maps)
            band = cfg.volume_band_m / scale
            rendered, _ = render_rays_neus(
                model, vo, vd, (vt - band).clamp_min(0.0), vt + band, cfg.volume_samples,
                cfg.volume_inv_s, gen,
            )
            loss_volume = (rendered - s.colors[vi]).abs().mean()
            loss = loss + cfg.w_volume_color * loss_volume
        parts = {"surface": loss_surface, "near": loss_near, "free": loss_free, "eikonal": loss_eik,
                 "normal": loss_normal, "color": loss_color, "volume_color": loss_volume, "edge": loss_edge,
                 "outline": loss_outline}
        if poses is not None:
            parts["pose"] = poses.regulariser() if maps is not None else torch.zeros((), device=device)
            loss = loss + parts["pose"]
        return loss, parts

    log.losses = optimise(model, cfg, loss_at, desc=f"train {info.name or 'field'}", progress=progress,
                          postfix={"surf": "surface", "col": "color"},
                          extra_groups=[poses.param_group()] if poses is not None else ())
    if visibility is not None:
        # Built by the same function as for a checkpoint that lacks it (Cache, attach_visibility),
        # so a field trained now and one given its grid later carry the same counts.
        model.visibility = visibility
    log.seconds = time.perf_counter() - t_start
    log.steps = cfg.steps
    model.info.provenance = {
        **model.info.provenance,
        "trained_from": "rgbd",
        "train_config": json.loads(json.dumps(asdict(cfg), default=str)),
        "train_seconds": round(log.seconds, 3),
        "train_frames": len(indices),
    }
    if poses is not None:
        log.pose_refinement = poses.report()
        log.corrected_poses = poses.camtoworld().detach().cpu().numpy()
        model.info.provenance["pose_refinement"] = {
            k: round(v, 4) if isinstance(v, float) else v for k, v in log.pose_refinement._asdict().items()
        }
    model.eval()
    return model, log
