"""Where a field's training views observed space: a dense voxel grid of view counts.

A field trained from a few views says nothing about the far side of an object, about space
behind a wall or outside every frustum. :class:`VisibilityGrid` records, for every voxel of
a dense grid over the field's bounds (field frame: the frame :meth:`Field.sdf` takes), how
many training views observed it, and :meth:`VisibilityGrid.observed` turns that into a
smooth weight in [0, 1] for any point.

What a view observes
--------------------
A pixel's ray observes space from the camera up to its depth hit plus a margin behind the
surface (``margin`` voxels, in z-depth as the depth image measures it, so that the observed
surface and the voxels just behind it that a trilinear lookup at the surface reads count as
observed), and, where the pixel has no depth hit (depth 0) in a capture whose zeros mean
empty, up to where the ray leaves the bounds; where zeros mean unknown (a sensor's missing
return, :attr:`regnf.captures.model.Capture.zero_depth_is_empty`) such a ray observes nothing.
Space behind a surface by more than the margin (occluded), outside the frustum
(including behind the camera) or outside the bounds is not observed. A view with lens
distortion projects through its lens (:class:`~regnf.observations.view_lenses.FrameLens`). A view counts once per
voxel however many of its rays cross it, so ``counts`` is the number of training views that
observed the voxel (independent of the image size and of ``pixel_stride``); unobserved
voxels have count 0.

The test is projective and exact per voxel centre, with no ray marching (hence no gaps
between diverging rays far from the camera): the centre ``c`` of a voxel, at z-depth ``z > 0``
in the camera of view ``k`` and projecting into pixel ``p`` of its image, is observed by
``k`` iff ``z <= d_p + m``, with ``d_p`` the depth of ``p`` (``inf`` for no hit) and ``m``
the margin in field units. It is the rule training's free-space term applies (see
``_ViewStack.seen_free`` in :mod:`regnf.training.training`), with the margin behind rather
than in front of the surface. Everything is vectorised over voxels; the only Python loops
are over frames and over slabs of voxels (:data:`_SLAB_VOXELS`).

Cost: a fraction of a second for a room capture's grid on one thread; on cores another job
keeps busy, torch's intra-op threads make it, like any torch workload, many times slower
(docs/decisions/field-training.md).

Storage: :func:`regnf.training.training.train_rgbd` attaches the grid of the capture it
trained on to the field (``field.visibility``; None for analytic and mesh-distilled fields,
meaning "everything observed"); checkpoints store it (``visibility.counts`` plus the
``visibility`` header block, see :mod:`regnf.io.checkpoint`); a checkpoint trained
elsewhere or before grids existed gets one from its capture, without retraining, with
:func:`regnf.io.checkpoint.attach_visibility`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from regnf.captures.distortion import Distortion, check_invertible, image_outline_rays
from regnf.captures.model import CaptureError
from regnf.core.box_grid import grid_shape
from regnf.core.errors import RegnfError
from regnf.observations.rgbd_samples import CaptureLike, capture_where, measured_depth
from regnf.observations.view_lenses import FrameLens

DEFAULT_RESOLUTION = 128
"""Voxels along the longest axis of the bounds (shorter axes get proportionally fewer)."""

DEFAULT_MARGIN = 2.0
"""Voxels (of the longest axis) behind an observed surface that still count as observed.

A trilinear lookup at a surface point reads voxel centres up to one voxel away along each
axis (up to sqrt 3 voxels deeper), so a margin of 2 keeps the observed surface at weight 1,
while space more than about 3 to 3.7 voxels behind it (by the view direction) reads 0."""

DEFAULT_FULL_COUNT = 2
"""Views after which a voxel counts as fully observed: weight ``min(count, k) / k``."""

MAX_COUNT = 255
"""Counts saturate here (uint8): far beyond any ``full_count``."""

_SLAB_VOXELS = 1 << 20
"""Voxels tested at a time per view: 4 MB temporaries, so memory is bounded at any
resolution, and operations large enough to be split over torch's intra-op threads (or to
fill a GPU). Single-threaded, slabs from 2**14 to 2**21 voxels cost the same within 20 %."""

_LOOKUP_CHUNK = 1 << 20
"""Points looked up at a time by :meth:`VisibilityGrid.observed`."""

_META_KEYS = ("resolution", "bounds", "margin", "full_count", "pixel_stride", "views")
"""Keys of :meth:`VisibilityGrid.to_json`, all required by :meth:`VisibilityGrid.parse_json`."""


class VisibilityGrid(torch.nn.Module):
    """How many training views observed each voxel of a box in the field frame.

    A module, so that ``field.visibility = grid`` makes it part of the field: ``field.to``
    moves it and ``field.state_dict()`` holds its counts (``visibility.counts``).

    Parameters
    ----------
    counts : (R_x, R_y, R_z) uint8 tensor
        Views that observed each voxel (saturating at :data:`MAX_COUNT`); voxel ``(i, j, k)``
        is the cell ``[lo + (i, j, k) * size, lo + (i + 1, j + 1, k + 1) * size)`` with
        ``size = (hi - lo) / (R_x, R_y, R_z)``, its count taken at its centre.
    bounds : (2, 3) float
        ``[lo, hi]`` of the grid in the field frame (the field's bounds when built by training).
    margin : float
        Voxels observed behind a surface (recorded: how the counts were made).
    full_count : int
        Views after which :meth:`observed` gives 1 (in [1, :data:`MAX_COUNT`]).
    pixel_stride : int
        Depth pixels pooled per lookup cell when the counts were made (recorded).
    views : int
        Training views that contributed (frames with depth).

    Raises
    ------
    ValueError
        Counts that are not a 3-D uint8 tensor, bounds that are not finite (2, 3) with
        min < max, a negative or non-finite margin, ``full_count`` outside [1, 255],
        ``pixel_stride < 1`` or ``views < 0``.
    """

    counts: torch.Tensor
    bounds: torch.Tensor

    def __init__(
        self,
        counts: torch.Tensor,
        bounds: torch.Tensor | Sequence,
        margin: float = DEFAULT_MARGIN,
        full_count: int = DEFAULT_FULL_COUNT,
        pixel_stride: int = 1,
        views: int = 0,
    ) -> None:
        super().__init__()
        if not isinstance(counts, torch.Tensor) or counts.ndim != 3 or counts.dtype != torch.uint8:
            what = (f"{counts.dtype} of shape {tuple(counts.shape)}"
                    if isinstance(counts, torch.Tensor) else type(counts).__name__)
            raise RegnfError(f"visibility counts must be a 3-D uint8 tensor, got {what}")
        if min(counts.shape) < 1:
            raise RegnfError(f"visibility counts need a voxel per axis, got {tuple(counts.shape)}")
        bounds = torch.as_tensor(bounds, dtype=torch.float32).to(counts.device)
        if not _is_box(bounds):
            raise RegnfError(
                f"visibility bounds must be finite (2, 3) with max > min, got {bounds.tolist()}"
            )
        if not (math.isfinite(margin) and margin >= 0):
            raise RegnfError(f"visibility margin must be finite and >= 0, got {margin}")
        if not 1 <= full_count <= MAX_COUNT:
            raise RegnfError(f"visibility full_count must be in [1, {MAX_COUNT}], got {full_count}")
        if pixel_stride < 1 or views < 0:
            raise RegnfError(
                f"visibility pixel_stride must be >= 1 and views >= 0, got {pixel_stride}, {views}"
            )
        self.margin, self.full_count = float(margin), int(full_count)
        self.pixel_stride, self.views = int(pixel_stride), int(views)
        self.register_buffer("counts", counts.contiguous())
        # Metadata (the checkpoint header holds it) and a derived lookup volume: moved by
        # .to() with the counts, never saved.
        self.register_buffer("bounds", bounds.clone(), persistent=False)
        self.register_buffer("_weights", self._weight_volume(self.full_count), persistent=False)

    # -- metadata -----------------------------------------------------------------------------
    @property
    def resolution(self) -> tuple[int, int, int]:
        """Voxels per axis ``(R_x, R_y, R_z)``."""
        return tuple(int(n) for n in self.counts.shape)  # type: ignore[return-value]

    @property
    def voxel_size(self) -> torch.Tensor:
        """(3,) float: edge lengths of a voxel in field units."""
        cells = torch.tensor(self.resolution, device=self.bounds.device)
        return (self.bounds[1] - self.bounds[0]) / cells

    def to_json(self) -> dict:
        """The grid's metadata (everything but the counts), JSON-serialisable."""
        return {
            "resolution": list(self.resolution),
            "bounds": self.bounds.tolist(),
            "margin": self.margin,
            "full_count": self.full_count,
            "pixel_stride": self.pixel_stride,
            "views": self.views,
        }

    @staticmethod
    def parse_json(data: object) -> dict:
        """Check metadata written by :meth:`to_json`, strictly, without touching any tensor.

        Parameters
        ----------
        data : object
            The parsed JSON.

        Returns
        -------
        dict
            ``resolution`` (tuple of 3 ints >= 1) and the keyword arguments of the constructor
            (``bounds`` as a (2, 3) float64 tensor). Size limits are the checkpoint reader's.

        Raises
        ------
        TypeError
            ``data`` is not an object.
        ValueError
            Unknown or missing keys, or a value of the wrong type or range (``"3"``, ``2.0``
            or ``true`` for an integer, non-finite numbers, min >= max).
        """
        if not isinstance(data, dict):
            raise TypeError(f"must be an object or null, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_META_KEYS))
        missing = [k for k in _META_KEYS if k not in data]
        if unknown or missing:
            raise RegnfError(f"unknown keys {unknown}, missing keys {missing}")

        def integer(key: str, value: object, low: int, high: int | None = None) -> int:
            # bool is an int subclass: true is not a resolution.
            wrong = isinstance(value, bool) or not isinstance(value, int)
            if wrong or value < low or (high is not None and value > high):
                span = f">= {low}" if high is None else f"in [{low}, {high}]"
                raise RegnfError(f"'{key}' must be an integer {span}, got {value!r:.40}")
            return value

        res = data["resolution"]
        if not isinstance(res, list) or len(res) != 3:
            raise RegnfError(f"'resolution' must be a list of 3 integers, got {res!r:.60}")
        resolution = tuple(integer("resolution", n, 1) for n in res)
        try:
            bounds = torch.tensor(data["bounds"], dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise RegnfError("'bounds' is not a numeric matrix") from exc
        if not _is_box(bounds):
            raise RegnfError(
                f"'bounds' must be finite (2, 3) with min < max, got {data['bounds']!r:.80}"
            )
        margin = data["margin"]
        number = not isinstance(margin, bool) and isinstance(margin, (int, float))
        if not (number and math.isfinite(margin) and margin >= 0):
            raise RegnfError(f"'margin' must be a finite number >= 0, got {margin!r:.40}")
        return {
            "resolution": resolution,
            "bounds": bounds,
            "margin": float(margin),
            "full_count": integer("full_count", data["full_count"], 1, MAX_COUNT),
            "pixel_stride": integer("pixel_stride", data["pixel_stride"], 1),
            "views": integer("views", data["views"], 0),
        }

    @classmethod
    def from_json(cls, data: object, counts: torch.Tensor) -> VisibilityGrid:
        """The grid of metadata ``data`` (see :meth:`to_json`) and ``counts``.

        Raises
        ------
        TypeError, ValueError
            Any of :meth:`parse_json`'s, or counts whose shape is not ``data["resolution"]``.
        """
        meta = cls.parse_json(data)
        resolution = meta.pop("resolution")
        if tuple(counts.shape) != resolution:
            raise RegnfError(
                f"counts have shape {tuple(counts.shape)}, the metadata's resolution "
                f"{list(resolution)}"
            )
        return cls(counts, **meta)

    def extra_repr(self) -> str:
        return (f"resolution={list(self.resolution)}, views={self.views}, margin={self.margin}, "
                f"full_count={self.full_count}")

    # -- lookups ------------------------------------------------------------------------------
    def _weight_volume(self, full_count: int) -> torch.Tensor:
        """(1, 1, R_z, R_y, R_x) float32 ``min(count, k) / k``, laid out for grid_sample."""
        w = self.counts.clamp(max=full_count).float() / float(full_count)
        # grid_sample reads (x, y, z) coordinates from the last, middle and first axes.
        return w.permute(2, 1, 0).contiguous()[None, None]

    @torch.no_grad()
    def observed(self, points: torch.Tensor, full_count: int | None = None) -> torch.Tensor:
        """How well the training views observed each point: a weight in [0, 1].

        The trilinear interpolation, between voxel centres, of ``min(count, k) / k`` with
        ``k = full_count`` views: 1 where ``k`` or more views saw the voxels around the point,
        ``1 / k`` per view in between, 0 where no view saw any of them (more than one voxel
        inside unobserved space: behind a surface by over ``margin + 1`` voxels, outside every
        frustum). Interpolating the saturated count rather than a 0/1 occupancy keeps one
        grazing view from counting as much as several, and keeps the weight continuous across
        voxel faces (registration steps do not jump). Within half a voxel of the bounds the
        outermost voxels' values are used; points outside the bounds (or not finite) are
        unobserved: 0.

        Parameters
        ----------
        points : (n, 3) float tensor
            Points in the field frame, on any device (looked up on the grid's, returned on
            theirs). No gradient flows.
        full_count : int, optional
            Views for weight 1 (default: :attr:`full_count`, saved with the grid).

        Returns
        -------
        (n,) float32 tensor
            On ``points``' device.
        """
        if not isinstance(points, torch.Tensor) or points.ndim != 2 or points.shape[-1] != 3:
            shape = (tuple(points.shape) if isinstance(points, torch.Tensor)
                     else type(points).__name__)
            raise RegnfError(f"points must be a (n, 3) tensor, got {shape}")
        k = self.full_count if full_count is None else int(full_count)
        if not 1 <= k <= MAX_COUNT:
            raise RegnfError(f"full_count must be in [1, {MAX_COUNT}], got {full_count}")
        volume = self._weights if k == self.full_count else self._weight_volume(k)
        device = self.counts.device
        lo, hi = self.bounds[0], self.bounds[1]
        out = torch.zeros(points.shape[0], device=device)
        for start in range(0, points.shape[0], _LOOKUP_CHUNK):
            x = points[start : start + _LOOKUP_CHUNK].detach()
            x = x.to(device=device, dtype=torch.float32)
            inside = ((x >= lo) & (x <= hi)).all(dim=-1)  # False for NaN
            # align_corners=False: -1 and 1 are the bounds, voxel centres at (i + 0.5) / R.
            g = ((x - lo) / (hi - lo) * 2.0 - 1.0).nan_to_num(0.0).clamp(-1.0, 1.0)
            w = F.grid_sample(volume, g.view(1, -1, 1, 1, 3), mode="bilinear",
                              padding_mode="border", align_corners=False).view(-1)
            out[start : start + x.shape[0]] = torch.where(inside, w, torch.zeros_like(w))
        return out.to(points.device)


def _is_box(bounds: torch.Tensor) -> bool:
    """``bounds`` is a finite (2, 3) box with max > min on every axis."""
    return (
        bounds.shape == (2, 3) and bool(torch.isfinite(bounds).all())
        and bool((bounds[1] > bounds[0]).all())
    )


def _frame_lookup(
    depth: np.ndarray, stride: int, margin: float, device: torch.device, zeros_empty: bool = True
) -> torch.Tensor:
    """(H + 2, W + 2) float32: per pixel, the deepest z-depth its ray observes; a ring of -inf.

    A hit at depth ``d`` observes up to ``d + margin``, a pixel without one (0) up to ``inf``
    where ``zeros_empty`` (the ray hit nothing) and nothing (``-inf``) where zeros are unknown,
    as does a NaN pixel (one the samples dropped: a flying pixel, confidence 0);
    with ``stride > 1`` every pixel of an s x s block takes the block's nearest hit, the
    conservative choice: a coarser stride never marks more space observed than stride 1. The
    ring of ``-inf`` around the image is where projections outside the frustum are sent, so
    that the observation test needs no separate frustum test.
    """
    d = torch.from_numpy(np.array(depth, dtype=np.float32)).to(device)
    # NaN (a pixel the samples dropped) is unknown even where zeros are empty.
    empty = (d == 0) if zeros_empty else torch.zeros_like(d, dtype=torch.bool)
    reach = torch.where(d > 0, d + margin, torch.where(empty, math.inf, -math.inf))
    if stride > 1:
        h, w = reach.shape
        pooled = -F.max_pool2d(-reach[None, None], stride, stride, ceil_mode=True)[0, 0]
        reach = pooled.repeat_interleave(stride, 0).repeat_interleave(stride, 1)[:h, :w]
    return F.pad(reach, (1, 1, 1, 1), value=-math.inf)


@torch.no_grad()
def build_visibility(
    capture: CaptureLike,
    bounds: torch.Tensor | Sequence,
    resolution: int = DEFAULT_RESOLUTION,
    margin: float = DEFAULT_MARGIN,
    pixel_stride: int = 1,
    device: torch.device | str = "cpu",
    indices: Sequence[int] | None = None,
    full_count: int = DEFAULT_FULL_COUNT,
) -> VisibilityGrid:
    """Count, per voxel of a grid over ``bounds``, the training views that observed it.

    See the module docstring for what a view observes. Frames without depth are skipped:
    nothing says where their rays stop, and counting them as seeing through to the bounds
    would mark occluded space observed.

    Parameters
    ----------
    capture : Capture
        A loaded capture (:func:`regnf.captures.formats.read_capture`): per frame ``K``,
        an OpenCV ``camtoworld`` and a z-depth in the capture's normalised frame, the frame a
        field trained on it by :func:`regnf.training.training.train_rgbd` lives in.
    bounds : (2, 3) float
        The grid's box in that frame (a trained field's ``bounds``).
    resolution : int
        Voxels along the longest axis of ``bounds``; shorter axes get proportionally fewer
        (at least 2), so voxels are about cubic.
    margin : float
        Voxels (edge of the largest voxel axis) behind each depth hit, in z-depth, that still
        count as observed (see :data:`DEFAULT_MARGIN`).
    pixel_stride : int
        Give each s x s block of depth pixels the block's nearest hit before the lookup. The
        cost is per voxel, so 1 (default) is hardly slower; a larger stride marks less space
        observed, never more.
    device : torch.device or str
        Where to count (CPU or CUDA); the grid is returned there.
    indices : sequence of int, optional
        Frames to use; default ``capture.train_indices()``.
    full_count : int
        Recorded as the grid's :attr:`VisibilityGrid.full_count`.

    Returns
    -------
    VisibilityGrid
        uint8 counts (saturating at 255) of shape :func:`regnf.core.box_grid.grid_shape`.

    Raises
    ------
    ValueError
        ``resolution``, ``pixel_stride`` or ``full_count`` < 1, a negative margin, bad bounds.
    CaptureError
        No frame to use, no frame with depth, or the capture's own error for a bad depth file.
    """
    if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
        raise RegnfError(f"visibility resolution must be an integer >= 1, got {resolution!r}")
    if isinstance(pixel_stride, bool) or not isinstance(pixel_stride, int) or pixel_stride < 1:
        raise RegnfError(f"pixel_stride must be an integer >= 1, got {pixel_stride!r}")
    if not (math.isfinite(margin) and margin >= 0):
        raise RegnfError(f"visibility margin must be finite and >= 0, got {margin}")
    device = torch.device(device)
    box_t = torch.as_tensor(bounds, dtype=torch.float32).detach().to("cpu")
    if not _is_box(box_t):
        raise RegnfError(f"bounds must be finite (2, 3) with max > min, got {box_t.tolist()}")
    if indices is None:
        indices = capture.train_indices()  # type: ignore[attr-defined]
    if len(indices) == 0:
        raise CaptureError(
            f"{capture_where(capture)}: no training frames to record visibility from"
        )
    shape = grid_shape(resolution, box_t[1] - box_t[0])
    box = box_t.double().numpy()
    size = (box[1] - box[0]) / np.asarray(shape, dtype=np.float64)
    margin_units = margin * float(size.max())
    # Voxel centres per axis (float64: 1-D, cheap).
    axes = [
        torch.from_numpy(box[0, a] + (np.arange(shape[a]) + 0.5) * size[a]).to(device)
        for a in range(3)
    ]
    counts = torch.zeros(shape, dtype=torch.int32, device=device)
    zeros_empty = bool(capture.zero_depth_is_empty)
    views = 0
    for i in indices:
        if capture.frames[i].depth_path is None:
            continue
        # The depth as the samples use it: the pixels they drop observe nothing either.
        depth = measured_depth(capture, i)
        views += 1
        frame = capture.frames[i]
        h, w = depth.shape
        lens = _lens(frame.distortion, frame.intrinsics, w, h)
        cells = _frustum_cells(frame.camtoworld, frame.intrinsics, w, h, box, shape, frame.distortion)
        if cells is not None:
            lookup = _frame_lookup(depth, pixel_stride, margin_units, device, zeros_empty)
            if lens is None:
                proj = _projection(frame.intrinsics, frame.camtoworld).to(device)
            else:
                # Camera coordinates: the lens takes them to pixels.
                proj = torch.from_numpy(np.linalg.inv(np.asarray(frame.camtoworld, np.float64))[:3, :4]).to(device)
            counts[cells] += _observed_by(lookup, proj, [axes[a][cells[a]] for a in range(3)], lens)
    if views == 0:
        raise CaptureError(
            f"{capture_where(capture)}: none of the {len(indices)} frames has depth: nothing says "
            "where their rays stop, so no visibility can be recorded"
        )
    # Saturated only now (int32 while counting): beyond 255 views a voxel is observed anyway.
    return VisibilityGrid(
        counts.clamp_(max=MAX_COUNT).to(torch.uint8), box_t.to(device), margin=margin,
        full_count=full_count, pixel_stride=pixel_stride, views=views,
    )


def _projection(K: np.ndarray, camtoworld: np.ndarray) -> torch.Tensor:
    """(3, 4) float64 ``K' [R | t]``: a field-frame point -> ``z (u + 1, v + 1, 1)``.

    ``K'`` is ``K`` with its principal point moved by one pixel, so that pixel coordinates
    index the lookup of :func:`_frame_lookup` (whose ``-inf`` ring comes first) directly; its
    last row keeps ``z``, the z-depth.
    """
    shifted = np.asarray(K, dtype=np.float64).copy()
    shifted[:2, 2] += 1.0
    w2c = np.linalg.inv(np.asarray(camtoworld, dtype=np.float64))
    return torch.from_numpy(shifted @ w2c[:3, :4])


def _lens(distortion: Distortion | None, K: np.ndarray, width: int, height: int) -> FrameLens | None:
    """The view's lens onto the pixels of :func:`_frame_lookup` (shifted by one); None: a pinhole."""
    if distortion is None:
        return None
    K = np.asarray(K, dtype=np.float64)
    shifted = K.copy()
    shifted[:2, 2] += 1.0
    return FrameLens(distortion, check_invertible(distortion, K, width, height), shifted)


def _frustum_cells(
    camtoworld: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    box: np.ndarray,
    shape: Sequence[int],
    distortion: Distortion | None = None,
) -> tuple[slice, slice, slice] | None:
    """Voxel index ranges (x, y, z) holding every voxel centre the view's frustum can contain.

    The frustum cut at the largest z-depth of the box's corners contains all of the box it
    sees; the AABB of its apex and four far corners (with a ``distortion``: its far outline,
    :func:`~regnf.captures.distortion.image_outline_rays`) bounds the work per view. None: the
    box lies behind the camera.
    """
    c2w = np.asarray(camtoworld, dtype=np.float64)
    w2c = np.linalg.inv(c2w)
    corners = np.array(
        [[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )
    z_far = float((corners @ w2c[:3, :3].T + w2c[:3, 3])[:, 2].max())
    if z_far <= 0:
        return None
    if distortion is None:
        pix = np.array([[0.0, 0.0, 1.0], [width, 0.0, 1.0], [0.0, height, 1.0], [width, height, 1.0]])
        rays = pix @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T  # z-depth 1
    else:
        rays = image_outline_rays(distortion, K, width, height)
    far = (rays * z_far) @ c2w[:3, :3].T + c2w[:3, 3]
    pts = np.vstack([c2w[:3, 3], far])
    size = (box[1] - box[0]) / np.asarray(shape, dtype=np.float64)
    # Voxel i's centre lies in [lo + i size, lo + (i + 1) size): one voxel of slack each way.
    lo = np.clip(np.floor((pts.min(0) - box[0]) / size).astype(np.int64) - 1, 0, shape)
    hi = np.clip(np.ceil((pts.max(0) - box[0]) / size).astype(np.int64) + 1, 0, shape)
    if (hi <= lo).any():
        return None
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))  # type: ignore[return-value]


def _observed_by(
    lookup: torch.Tensor, proj: torch.Tensor, axes: Sequence[torch.Tensor], lens: FrameLens | None = None
) -> torch.Tensor:
    """(n_x, n_y, n_z) bool: whether the view observes the voxel centre at ``(i, j, k)``.

    Parameters
    ----------
    lookup : (H + 2, W + 2) float32
        The view's :func:`_frame_lookup`.
    proj : (3, 4) float64
        The view's :func:`_projection`; with a ``lens``, its world -> camera ``[R | t]``.
    axes : three (n_a,) float64
        Voxel-centre coordinates per axis: centre ``(i, j, k)`` is
        ``(axes[0][i], axes[1][j], axes[2][k])``.
    """
    hp, wp = lookup.shape
    # Pixel indices in float are exact below 2**24; larger images project in float64.
    dtype = torch.float32 if hp * wp <= 2**24 else torch.float64
    flat_lookup = lookup.reshape(-1)
    # A voxel centre's projection is a sum of three per-axis terms (computed in float64 on
    # 1-D vectors, so that far-away translations lose nothing): no (n, 3) array is built.
    terms = [(proj[:, a, None] * axes[a][None]).to(dtype) for a in range(3)]
    yz = [terms[1][c][:, None] + terms[2][c][None, :] + float(proj[c, 3]) for c in range(3)]
    n_x = axes[0].shape[0]
    out = torch.empty((n_x, *yz[0].shape), dtype=torch.bool, device=lookup.device)
    slab = max(1, _SLAB_VOXELS // yz[0].numel())
    for x0 in range(0, n_x, slab):
        xs = slice(x0, min(n_x, x0 + slab))
        qx, qy, qz = (terms[0][c][xs, None, None] + yz[c][None] for c in range(3))
        front = qz > 1e-6
        inv_z = torch.where(front, qz, 1.0).reciprocal_()
        # Outside the image, or behind the camera: the -inf ring (index 0), never observed.
        if lens is None:
            u = qx.mul_(inv_z).floor_().clamp_(0, wp - 1)
            v = qy.mul_(inv_z).floor_().clamp_(0, hp - 1)
        else:
            u, v = lens.pixels(qx.mul_(inv_z), qy.mul_(inv_z))
            u, v = u.floor_().clamp_(0, wp - 1), v.floor_().clamp_(0, hp - 1)
        pixel = torch.where(front, v.mul_(wp).add_(u), 0.0).to(torch.int32)
        # index_select with int32 indices: faster than advanced indexing (int64)
        # (docs/decisions/implementation-speed.md).
        out[xs] = qz <= flat_lookup.index_select(0, pixel.view(-1)).view_as(qz)
    return out
