"""The cameras of a generated data set's variants: an orbit turned per seed, or a capture's frames.

``camera_source`` ``orbit``: the configured orbit inside the scene's bounds, turned by a seeded
azimuth per variant when ``jitter_cameras``. ``capture``: the frames of the capture the user
names (any capture format), resized to the data set's view width at the capture's aspect
ratio; each variant a seeded choice of ``cameras.n`` frames, or the same evenly spaced ones.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from regnf.compositor.cameras_io import orbit_around_bounds
from regnf.compositor.render_folder import check_image_size
from regnf.core.errors import RegnfError
from regnf.render.camera import Camera

if TYPE_CHECKING:
    from .generate_config import GenerateConfig


CAPTURE_FRAMES_STREAM = 11
"""Second seed word of a variant's random choice of capture frames (``default_rng([seed,
STREAM])``): a stream of its own, apart from the orbit's turn (1), the appearance's
(:data:`regnf.datasets.variation.STREAM`, 7) and the placement's (:data:`regnf.datasets.placement_jitter.STREAM`,
13), so none changes what another draws."""


class CaptureViews(NamedTuple):
    """The capture whose frames are the variants' cameras (``camera_source`` ``capture``)."""

    path: Path
    """The capture folder (or metadata file) the user named, absolute."""
    cameras: list[Camera]
    """Every frame's camera, in file order, posed in metres, resized to the data set's view size."""
    identity: dict[str, Any]
    """What of the capture the variants depend on: its frame count, image size and a digest of
    its frames' cameras (part of the data set's config_key, so another capture is refused on resume)."""


def capture_views(config: GenerateConfig) -> CaptureViews | None:
    """The capture of ``config.capture`` with its cameras at the data set's view size (None for
    orbit cameras): read and checked before any work.

    Raises
    ------
    ValueError
        The folder is missing or not a capture (a :class:`regnf.captures.model.CaptureError`
        naming the file); it has fewer frames than ``cameras.n``; a view would be too large.
    """
    if config.camera_source != "capture":
        return None
    from regnf.captures.formats import read_capture
    from regnf.compositor.cameras_io import capture_cameras, resized, target_size

    assert config.capture is not None  # GenerateConfig refuses capture cameras without it
    path = Path(config.capture).absolute()
    capture, _ = read_capture(path)
    meta = capture.root / capture.meta_name
    frames = len(capture.frames)
    if config.cameras.n > frames:
        raise RegnfError(f"{meta}: the capture has {frames} frames, fewer than the {config.cameras.n} views per "
                         f"variant (cameras.n); ask for at most {frames}")
    width, height = target_size(capture.width, capture.height, config.cameras.width, None)
    check_image_size(width, height, f"cameras: a view of {meta} at width {width}")
    native = capture_cameras(capture)
    digest = hashlib.sha256(json.dumps([[np.round(np.asarray(c.K, np.float64), 6).tolist(),
                                         np.round(np.asarray(c.camera_to_world, np.float64), 9).tolist()]
                                        for c in native]).encode()).hexdigest()
    identity = {"frames": frames, "width": capture.width, "height": capture.height, "cameras_sha256": digest}
    same = (width, height) == (capture.width, capture.height)
    return CaptureViews(path, [c if same else resized(c, width, height) for c in native], identity)


def at_capture_size(config: GenerateConfig, capture: CaptureViews | None) -> GenerateConfig:
    """``config`` with ``cameras.height`` the height of ``capture``'s views (their width is
    ``cameras.width``, the height is the capture's aspect ratio's): the size the views have, in
    the recorded settings and the disk estimate. ``config`` itself for orbit cameras."""
    if capture is None or config.cameras.height == capture.cameras[0].height:
        return config
    return dataclasses.replace(config, cameras=dataclasses.replace(config.cameras, height=capture.cameras[0].height))


def variant_frames(config: GenerateConfig, seed: int, frames: int) -> list[int]:
    """The capture frames (indices, increasing) of variant ``seed``'s views, of a capture of
    ``frames`` frames: ``cameras.n`` of them, a seeded random choice without repeats when
    ``jitter_cameras``, else evenly spaced from the first frame to the last (every variant the same).

    Raises
    ------
    ValueError
        ``cameras.n`` is more than ``frames``.
    """
    n = config.cameras.n
    if n > frames:
        raise RegnfError(f"{n} views per variant from a capture of {frames} frames")
    if config.jitter_cameras:
        rng = np.random.default_rng([seed, CAPTURE_FRAMES_STREAM])
        return sorted(int(i) for i in rng.choice(frames, size=n, replace=False))
    # Steps of at least one frame: rounding half up keeps them apart.
    return [math.floor(float(x) + 0.5) for x in np.linspace(0.0, frames - 1.0, n)]


def variant_cameras(bounds: np.ndarray, config: GenerateConfig, seed: int,
                    capture: CaptureViews | None = None) -> list[Camera]:
    """The cameras of variant ``seed``: the configured orbit, turned by a seeded azimuth if jittered,
    or with ``capture`` (capture cameras) the frames of :func:`variant_frames`."""
    if capture is not None:
        return [capture.cameras[i] for i in variant_frames(config, seed, len(capture.cameras))]
    orbit = config.cameras
    if config.jitter_cameras:
        # A generator of its own (not the replacement choices'), so the choices stay those of
        # `regnf replace --seed`.
        rng = np.random.default_rng([seed, 1])
        offset = orbit.azimuth_offset_deg + float(rng.uniform(0.0, 360.0 / orbit.n))
        orbit = dataclasses.replace(orbit, azimuth_offset_deg=offset)
    return orbit_around_bounds(bounds, orbit)
