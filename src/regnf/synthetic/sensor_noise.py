"""An RGB-D sensor noise model for the synthetic captures, at four named levels.

The depth pieces, applied in this order to a rendered z-depth image by
:func:`apply_sensor_noise` (a depth of 0 means "no return" throughout):

1. lateral noise (ICL-NUIM, Handa et al. 2014): each pixel reads the clean depth (bilinearly
   resampled within a surface; across a depth edge, the nearest pixel's: a shifted sample
   lands on one surface, never between two) at a position jittered by a Gaussian whose
   standard deviation is a multiple of the lateral sigma of Nguyen et al. 2012,
   ``sigma_L(theta) = 0.8 + 0.035 theta / (pi/2 - theta)`` pixels of the depth camera
   (:func:`lateral_sigma_px`; in metres ``sigma_L z / f`` with the depth camera's focal length
   ``f``, so an image rendered with another focal length is jittered by ``sigma_L f_image / f``
   of its own pixels);
2. axial noise (Nguyen, Izadi, Lovell 2012, "Modeling Kinect Sensor Noise for Improved 3D
   Reconstruction and Tracking"): Gaussian with ``sigma_z(z, theta) = 0.0012 + 0.0019 (z -
   0.4)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2`` metres
   (:func:`regnf.captures.depth_uncertainty.axial_sigma`, the model training weights its depth
   terms by), z in metres and theta the angle between the ray and the surface normal;
3. disparity quantisation (ICL-NUIM): ``d = b f / z`` rounded to a fraction of a pixel, then
   back to depth;
4. millimetre quantisation of the reported depth;
5. no return: at grazing angles, in a band of ``edge_band_px`` pixels of the depth camera on
   each side of a depth discontinuity (:func:`edge_band`), beyond the maximum range, and at
   random speckle pixels.

The colour gets a random exposure gain per frame. The camera poses get SLAM-like errors
(:mod:`regnf.synthetic.pose_noise`). :data:`NOISE_LEVELS` names the four levels a capture is
made at: ``ideal`` (nothing), ``sensor`` (the noise models and a per-frame pose jitter),
``slam`` (``sensor`` plus pose drift) and ``harsh`` (twice the noise, 10 % speckle and more
drift).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from regnf.captures.depth_uncertainty import MAX_THETA, DepthNoiseModel, axial_sigma
from regnf.core.atomic_io import write_json
from regnf.synthetic.pose_noise import PoseNoiseConfig, perturb_poses

NOISE_MODEL_VERSION = 4
"""Version of what :func:`apply_sensor_noise` makes of a level's settings: part of a noisy
capture's cache key, raised when the code changes the frames a level gives."""

TRUE_POSES_NAME = "poses_true.json"
"""File beside a noisy capture's ``meta_data.json`` with the poses its images were rendered
from (for evaluation; training reads only ``meta_data.json``)."""


@dataclass(frozen=True)
class SensorNoiseConfig:
    """What a capture's sensor adds to the rendered images and poses (defaults: nothing)."""

    axial_scale: float = 0.0
    """Multiplier on Nguyen et al.'s axial sigma_z(z, theta) (0: no axial noise)."""
    lateral_scale: float = 0.0
    """Multiplier on Nguyen et al.'s lateral sigma_L(theta), 0 for none (docs/decisions/sensor-noise.md)."""
    baseline_m: float = 0.075
    """Projector-camera baseline of the disparity, metres."""
    disparity_focal_px: float = 580.0
    """Focal length of the depth camera, pixels (a Kinect's infrared camera): the unit of the disparity and of the lateral noise."""
    disparity_step_px: float = 0.0
    """Quantisation step of the disparity, pixels (0: none)."""
    depth_step_m: float = 0.0
    """Quantisation step of the reported depth, metres (0: none)."""
    max_incidence_deg: float = 90.0
    """No return where the angle between the ray and the surface normal exceeds this, degrees."""
    edge_jump_footprints: float = math.inf
    """A pixel is at a depth edge where its 3x3 window's depth range (no return as 0) exceeds this many pixel footprints (z / fx)."""
    edge_band_px: float = 1.0
    """Width of the no-return band on each side of a depth edge, pixels of the depth camera (docs/decisions/sensor-noise.md)."""
    max_range_m: float = math.inf
    """No return beyond this depth, metres."""
    speckle: float = 0.0
    """Fraction of the pixels given no return at random."""
    exposure_sigma: float = 0.0
    """Standard deviation of the natural log of each frame's colour gain (0: none)."""
    pose: PoseNoiseConfig = dataclasses.field(default_factory=PoseNoiseConfig)
    """Error of the stored camera poses."""


_SENSOR = SensorNoiseConfig(
    axial_scale=1.0,
    lateral_scale=0.625,
    disparity_step_px=1.0 / 8.0,
    depth_step_m=0.001,
    max_incidence_deg=80.0,
    # A plane at 80 degrees spans 2 tan(80) = 11.3 footprints over 3 pixels: only real jumps exceed 12.
    edge_jump_footprints=12.0,
    max_range_m=8.0,
    speckle=0.01,
    exposure_sigma=0.05,
    pose=PoseNoiseConfig(jitter_m=0.001, jitter_deg=0.05),
)

NOISE_LEVELS: dict[str, SensorNoiseConfig] = {
    "ideal": SensorNoiseConfig(),
    "sensor": _SENSOR,
    "slam": dataclasses.replace(
        _SENSOR, pose=PoseNoiseConfig(jitter_m=0.001, jitter_deg=0.05, drift_m=0.01, drift_deg=0.3)
    ),
    "harsh": dataclasses.replace(
        _SENSOR,
        axial_scale=2.0,
        lateral_scale=1.25,
        speckle=0.10,
        exposure_sigma=0.10,
        pose=PoseNoiseConfig(jitter_m=0.002, jitter_deg=0.1, drift_m=0.03, drift_deg=1.0),
    ),
}
"""The capture noise levels by name: ideal, sensor, slam, harsh."""


def lateral_sigma_px(theta: np.ndarray) -> np.ndarray:
    """Nguyen et al.'s lateral noise sigma_L(theta), pixels of the depth camera (theta in radians, clamped)."""
    theta = np.minimum(np.asarray(theta, dtype=np.float64), MAX_THETA)
    return 0.8 + 0.035 * theta / (np.pi / 2 - theta)


SURFACE_STEP_FOOTPRINTS = 6.0
"""Largest depth step between neighbouring pixels, in pixel footprints (z / fx), taken as one
surface (a plane at 80.5 degrees steps that far): by :func:`incidence_angles` where the step
changes across the pixel, and by the lateral noise's resampling."""


def _tangent(points: np.ndarray, depth: np.ndarray, axis: int, footprint: np.ndarray) -> np.ndarray:
    """(H, W, 3) tangent of the surface at each pixel along image ``axis`` (1: columns, 0: rows).

    With ``step`` = :data:`SURFACE_STEP_FOOTPRINTS` x ``footprint`` (z / fx per pixel): the
    central difference where the depth changes alike on both sides (a plane, grazing or not:
    steps of one sign that differ by at most ``step`` or half the smaller); at a depth edge,
    the one-sided difference toward the neighbour on the pixel's own surface (the smaller
    step, if at most ``step``); where both neighbours lie on other surfaces or give no return
    (a structure one pixel wide), one footprint sideways, as on a surface facing the camera
    along that axis: nothing in the image says otherwise.
    """
    h, w = depth.shape
    step = SURFACE_STEP_FOOTPRINTS * footprint
    # Beyond the image the surface goes on as it left it: linear extrapolation.
    pad_p = np.pad(points, ((1, 1), (1, 1), (0, 0)), mode="reflect", reflect_type="odd")
    pad_z = np.pad(depth, 1, mode="reflect", reflect_type="odd")
    if axis == 1:
        fwd_p, bwd_p, fwd_z, bwd_z = pad_p[1:-1, 2:], pad_p[1:-1, :-2], pad_z[1:-1, 2:], pad_z[1:-1, :-2]
    else:
        fwd_p, bwd_p, fwd_z, bwd_z = pad_p[2:, 1:-1], pad_p[:-2, 1:-1], pad_z[2:, 1:-1], pad_z[:-2, 1:-1]
    fwd = np.where(fwd_z > 0, fwd_z - depth, np.nan)
    bwd = np.where(bwd_z > 0, depth - bwd_z, np.nan)
    with np.errstate(invalid="ignore"):
        # Alike: steps of one sign that differ by at most a footprint step or half their size
        # (a plane's steps grow with perspective, steeply at grazing angles). False where a
        # side has no return.
        spread = np.maximum(step, 0.5 * np.minimum(np.abs(fwd), np.abs(bwd)))
        alike = (fwd * bwd >= 0) & (np.abs(fwd - bwd) <= spread)
        fwd_ok = np.abs(fwd) <= step
        bwd_ok = np.abs(bwd) <= step
    use_fwd = fwd_ok & (~bwd_ok | (np.abs(np.nan_to_num(fwd)) <= np.abs(np.nan_to_num(bwd))))
    facing = np.zeros((h, w, 3))
    facing[..., 1 - axis] = footprint
    tangent = np.where(use_fwd[..., None], fwd_p - points, np.where(bwd_ok[..., None], points - bwd_p, facing))
    return np.where(alike[..., None], 0.5 * (fwd_p - bwd_p), tangent)


def incidence_angles(depth: np.ndarray, K: np.ndarray, normals_cam: np.ndarray | None = None) -> np.ndarray:
    """Angle between each pixel's ray and the surface normal, radians in [0, pi/2].

    Parameters
    ----------
    depth : (H, W) float
        z-depth, metres (0: no return).
    K : (3, 3) float
        Intrinsics; pixel centres at (u + 0.5, v + 0.5).
    normals_cam : (H, W, 3) float, optional
        Surface normals in the camera frame (either orientation). None: the normals of the
        depth image's local tangent plane (cross product of the tangents of :func:`_tangent`
        along rows and columns), exact on planar surfaces, at their edges too; the
        neighbours across a depth edge belong to other surfaces and are not used.

    Returns
    -------
    (H, W) float64
        Meaningless where the pixel has no return.
    """
    h, w = depth.shape
    # Rays with a camera z of 1 (as the renderer casts them), so that a point is ray * z-depth;
    # numpy here, as a frame's worth of torch ops is slow on a busy CPU.
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    if normals_cam is None:
        z = np.asarray(depth, np.float64)
        points = rays * z[..., None]
        footprint = z / K[0, 0]
        normals_cam = np.cross(_tangent(points, z, 1, footprint), _tangent(points, z, 0, footprint))
    norm = np.linalg.norm(normals_cam, axis=-1) * np.linalg.norm(rays, axis=-1)
    cos = np.abs((normals_cam * rays).sum(-1)) / np.maximum(norm, 1e-300)
    return np.arccos(np.clip(cos, 0.0, 1.0))


def _neighbourhood(image: np.ndarray, mode: str) -> np.ndarray:
    """(9, H, W) each pixel's 3x3 window of ``image`` (H, W); beyond the border as ``np.pad``'s ``mode``."""
    h, w = image.shape
    pad = np.pad(image, 1, mode=mode)
    return np.stack([pad[i : i + h, j : j + w] for i in range(3) for j in range(3)])


def depth_edges(depth: np.ndarray, K: np.ndarray, footprints: float) -> np.ndarray:
    """(H, W) bool: pixels with a return whose 3x3 depth range exceeds ``footprints * z / fx``.

    A no-return neighbour counts as depth 0 (so a pixel beside a hole is an edge); beyond the
    image border the nearest pixel is repeated.
    """
    windows = _neighbourhood(depth, "edge")
    spread = windows.max(0) - windows.min(0)
    return (depth > 0) & (spread > footprints * depth / K[0, 0])


def edge_band(edges: np.ndarray, valid: np.ndarray, width_px: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool: the pixels lost in a band ``width_px`` image pixels wide beside depth edges.

    Ring 1 is the ``edges`` themselves (the pixels on either side of a jump), ring k + 1 the
    pixels with a return that touch ring k (8-neighbourhood). The first ``floor(width_px)``
    rings are lost whole and the next one pixel by pixel with probability ``width_px -
    floor(width_px)``: a band narrower than an image pixel (a depth camera finer than the
    rendered image) loses that share of the edge pixels, so the lost width in metres is the
    sensor's on average.

    Parameters
    ----------
    edges : (H, W) bool
        :func:`depth_edges`.
    valid : (H, W) bool
        Pixels with a return (the band grows only through them).
    width_px : float
        Band width on each side, pixels of this image (>= 0).
    rng : numpy.random.Generator
        Draws one (H, W) uniform image when the band ends inside a ring.
    """
    whole, part = math.floor(width_px), width_px - math.floor(width_px)
    lost = np.zeros(edges.shape, dtype=bool)
    reach, ring = edges, edges
    for k in range(1, whole + 2):  # per ring of pixels, each ring vectorised
        if k > 1:
            grown = _neighbourhood(reach, "constant").any(0) & valid
            ring, reach = grown & ~reach, grown | reach
        if k <= whole:
            lost |= ring
        elif part > 0:
            lost |= ring & (rng.random(ring.shape) < part)
    return lost


def _resample(depth: np.ndarray, x: np.ndarray, y: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``depth`` read at continuous pixel indices (x column, y row), clamped to the image.

    Bilinear where the four taps have returns on one surface (their depths within ``step``);
    elsewhere the nearest tap's depth (0 if it has no return): a shifted sample lands on one
    of the surfaces beside a depth edge, never at a depth between them.

    Parameters
    ----------
    depth : (H, W) float
        0: no return.
    x, y : (H, W) float
    step : (H, W) float
        Largest depth range of one surface's taps, the units of ``depth``.
    """
    h, w = depth.shape
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros(x.shape, np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros(y.shape, np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    taps = np.stack([depth[y0, x0], depth[y0, x1], depth[y1, x0], depth[y1, x1]])
    value = (taps[0] * (1 - fx) + taps[1] * fx) * (1 - fy) + (taps[2] * (1 - fx) + taps[3] * fx) * fy
    one_surface = (taps > 0).all(0) & (taps.max(0) - taps.min(0) <= step)
    nearest = np.take_along_axis(taps, (2 * (fy >= 0.5) + (fx >= 0.5))[None], 0)[0]
    return np.where(one_surface, value, nearest)


def apply_sensor_noise(
    depth: np.ndarray,
    normals_cam: np.ndarray | None,
    rgb: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    config: SensorNoiseConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """One frame as the sensor of ``config`` would report it (see the module for the pieces).

    Parameters
    ----------
    depth : (H, W) float
        Clean z-depth, metres; 0 means no return.
    normals_cam : (H, W, 3) float or None
        Surface normals in the camera frame; None: from the depth (:func:`incidence_angles`).
    rgb : (H, W, 3) uint8 or float
        Colour (uint8, or float in [0, 1]); the dtype is kept.
    K : (3, 3) float
        Intrinsics of the image; pixel centres at (u + 0.5, v + 0.5).
    rng : numpy.random.Generator
        Source of every random draw.
    config : SensorNoiseConfig

    Returns
    -------
    depth : (H, W) float32
        Noisy z-depth, metres; 0 means no return.
    rgb : (H, W, 3)
        The colour times one random exposure gain, clipped to the dtype's range.
    """
    clean = np.asarray(depth, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    h, w = clean.shape
    valid = clean > 0
    theta = incidence_angles(clean, K, normals_cam)
    z = clean
    if config.lateral_scale > 0:
        # Nguyen's sigma_L is in the depth camera's pixels: the same metric jitter in this image's.
        sigma = config.lateral_scale * lateral_sigma_px(theta) * (K[0, 0] / config.disparity_focal_px)
        cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        jitter = rng.standard_normal((2, h, w)) * sigma
        step = SURFACE_STEP_FOOTPRINTS * clean / K[0, 0]
        z = np.where(valid, _resample(clean, cols + jitter[0], rows + jitter[1], step), 0.0)
    if config.axial_scale > 0:
        noise = rng.standard_normal((h, w)) * (config.axial_scale * axial_sigma(z, theta))
        z = np.where(z > 0, z + noise, 0.0)  # a pixel without a return gets none from noise
    z = np.where(z > 0, z, 0.0)
    if config.disparity_step_px > 0:
        bf = config.baseline_m * config.disparity_focal_px
        disparity = np.round(bf / np.maximum(z, 1e-12) / config.disparity_step_px) * config.disparity_step_px
        z = np.where((z > 0) & (disparity > 0), bf / np.maximum(disparity, 1e-300), 0.0)
    if config.depth_step_m > 0:
        z = np.round(z / config.depth_step_m) * config.depth_step_m
    keep = valid & (z > 0) & (z <= config.max_range_m)
    keep &= theta <= math.radians(config.max_incidence_deg)
    if math.isfinite(config.edge_jump_footprints):
        # The band is in the depth camera's pixels, as the lateral noise: this image's share of it.
        band = config.edge_band_px * K[0, 0] / config.disparity_focal_px
        keep &= ~edge_band(depth_edges(clean, K, config.edge_jump_footprints), valid, band, rng)
    if config.speckle > 0:
        keep &= rng.random((h, w)) >= config.speckle
    out_depth = np.where(keep, z, 0.0).astype(np.float32)
    out_rgb = np.asarray(rgb)
    if config.exposure_sigma > 0:
        gain = math.exp(config.exposure_sigma * rng.standard_normal())
        top = 255.0 if out_rgb.dtype == np.uint8 else 1.0
        scaled = np.clip(out_rgb.astype(np.float64) * gain, 0.0, top)
        out_rgb = (np.rint(scaled) if out_rgb.dtype == np.uint8 else scaled).astype(out_rgb.dtype)
    return out_depth, out_rgb


def depth_noise_model(config: SensorNoiseConfig, fx: float) -> DepthNoiseModel:
    """The noise model of the depth ``config`` makes at an image focal length ``fx`` (pixels).

    The axial sigma scaled by ``axial_scale`` (the default's where there is no axial noise: its
    quantisation still errs) and the lateral sigma at normal incidence in the image's own pixels:
    what a capture made at this level names in its metadata (``regnf.depth_noise``).
    """
    model = DepthNoiseModel() if config.axial_scale == 0 else DepthNoiseModel().scaled(config.axial_scale)
    lateral = config.lateral_scale * float(lateral_sigma_px(0.0)) * fx / config.disparity_focal_px
    return dataclasses.replace(model, lateral_px=lateral)


def noisy_capture_frames(
    rgbs: Sequence[np.ndarray],
    depths: Sequence[np.ndarray],
    c2w: np.ndarray,
    K: np.ndarray,
    config: SensorNoiseConfig,
    seed: int,
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """A rendered capture as the sensor and SLAM of ``config`` would deliver it.

    Parameters
    ----------
    rgbs, depths : sequences of (H, W, 3) uint8 and (H, W) float
        Frames rendered from the true poses (depth in metres, 0: no return).
    c2w : (n, 4, 4) float
        True camera-to-world poses, metres.
    K : (3, 3) float
    config : SensorNoiseConfig
    seed : int
        Seed of every draw (poses first, then the frames in order).

    Returns
    -------
    rgbs : list of (H, W, 3) uint8
    depths : list of (H, W) float32
    c2w : (n, 4, 4) float64
        The perturbed poses to store with the frames.
    """
    rng = np.random.default_rng(seed)
    poses = perturb_poses(c2w, config.pose, rng)
    out_rgb, out_depth = [], []
    for rgb, depth in zip(rgbs, depths):  # per frame
        d, c = apply_sensor_noise(depth, None, rgb, K, rng, config)
        out_rgb.append(c)
        out_depth.append(d)
    return out_rgb, out_depth, poses


def write_true_poses(out_dir: str | Path, c2w: np.ndarray, level: str, seed: int) -> Path:
    """Write the true poses of a noisy capture to ``out_dir``/:data:`TRUE_POSES_NAME`.

    Parameters
    ----------
    out_dir : str or Path
        The capture folder.
    c2w : (n, 4, 4) float
        True OpenCV camera-to-world poses, metres (compare with
        :meth:`~regnf.captures.model.Capture.camtoworld_metres`).
    level, seed : str, int
        The noise level's name and seed, recorded with the poses.

    Returns
    -------
    Path
        The written file: ``{"noise", "noise_seed", "camtoworld_metres": (n, 4, 4) lists}``.
    """
    path = Path(out_dir) / TRUE_POSES_NAME
    poses = np.asarray(c2w, dtype=np.float64)
    write_json(path, {"noise": level, "noise_seed": int(seed), "camtoworld_metres": poses.tolist()})
    return path
