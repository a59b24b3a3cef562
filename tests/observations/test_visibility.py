"""Visibility grids against closed-form truth, their checkpoint storage and the cache upgrade.

The scene is an axis-aligned box (the analytic :class:`~regnf.fields.analytic.Box`) seen by
cameras placed by hand; depths are exact ray-box intersections computed here in float64
(independent of the code under test), written in metres through a known similarity and
loaded back, so the grid is checked in the capture's normalised frame, the field frame.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from regnf.captures.model import Capture, CaptureError
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.fields.analytic import Box
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig
from regnf.io.checkpoint import (
    DIGEST_KEY,
    HEADER_KEY,
    VISIBILITY_KEY,
    VISIBILITY_TENSOR,
    ArchitectureLimits,
    CheckpointError,
    attach_visibility,
    content_digest,
    load_field,
    read_header,
    save_field,
    verify_checkpoint,
)
from regnf.observations.visibility import VisibilityGrid, build_visibility
from regnf.synthetic import cache as cache_module
from regnf.synthetic.cache import Cache, reusable
from regnf.training.training import RGBDTrainConfig

from .capture_helpers import WORLD_OFFSET, WORLD_SCALE, WORLDTOGT

BOX_HALF = 0.3
"""The box is [-0.3, 0.3]^3 in the normalised frame."""
BOUNDS = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RES = 40
"""Voxels per axis over BOUNDS: 0.05 wide, centres at odd multiples of 0.025."""
VOXEL = 2.0 / RES
W = H = 48
FOCAL = 40.0
"""Half field of view atan(24 / 40) = 31 degrees: a camera sees |x|, |y| <= 0.6 z."""
K = np.array([[FOCAL, 0.0, W / 2], [0.0, FOCAL, H / 2], [0.0, 0.0, 1.0]])


def pose(eye: tuple[float, float, float], right: tuple, down: tuple, forward: tuple) -> np.ndarray:
    """OpenCV cam-to-world (normalised frame) with the given camera axes (world vectors)."""
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


CAM_A = pose((0.0, 0.0, -0.9), (1, 0, 0), (0, 1, 0), (0, 0, 1))
"""In front of the box's z = -0.3 face, looking +z: sees that face at z-depth 0.6."""
CAM_B = pose((-0.9, 0.0, 0.0), (0, 0, -1), (0, 1, 0), (1, 0, 0))
"""In front of the x = -0.3 face, looking +x: sees that face at z-depth 0.6."""
CAM_C = pose((0.5, -0.5, 0.7), (1, 0, 0), (0, 1, 0), (0, 0, 1))
"""Beyond the box, looking +z (away from it): no pixel has a hit; it sees z in (0.7, 1]."""
CAMERAS = (CAM_A, CAM_B, CAM_C)


def box_depth(c2w: np.ndarray, dirs_cam: np.ndarray) -> np.ndarray:
    """Exact z-depth (n,) where rays with camera directions ``dirs_cam`` (n, 3), z = 1, enter
    the box; inf where they miss it (slab method, float64)."""
    o = c2w[:3, 3]
    d = dirs_cam @ c2w[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (-BOX_HALF - o) / d
        t1 = (BOX_HALF - o) / d
    t_in = np.nanmax(np.minimum(t0, t1), axis=1)
    t_out = np.nanmin(np.maximum(t0, t1), axis=1)
    # dirs have z = 1 in the camera, so the ray parameter is the z-depth.
    return np.where((t_out >= t_in) & (t_in > 0), t_in, np.inf)


def depth_image(c2w: np.ndarray) -> np.ndarray:
    """(H, W) z-depth through pixel centres, 0 where the ray misses the box."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dirs = np.stack([(u - K[0, 2]) / FOCAL, (v - K[1, 2]) / FOCAL, np.ones_like(u)], -1).reshape(-1, 3)
    z = box_depth(c2w, dirs)
    return np.where(np.isfinite(z), z, 0.0).reshape(H, W)


def write_box_capture(root: Path, cameras=CAMERAS, with_depth: bool = True) -> Capture:
    """The box seen by ``cameras``, written in metres (WORLDTOGT) and loaded back."""
    poses_m = np.stack([c.copy() for c in cameras])
    poses_m[:, :3, 3] = poses_m[:, :3, 3] * WORLD_SCALE + WORLD_OFFSET
    depths = [depth_image(c) * WORLD_SCALE for c in cameras] if with_depth else None
    rgbs = [np.zeros((H, W, 3), np.uint8) for _ in cameras]
    write_capture(root, rgbs, depths, poses_m, K, WORLDTOGT, meta={"zero_depth": "empty"})
    return load_capture(root)


def voxel_centres() -> np.ndarray:
    """(RES, RES, RES, 3) float64 voxel centres over BOUNDS."""
    c = -1.0 + (np.arange(RES) + 0.5) * VOXEL
    return np.stack(np.meshgrid(c, c, c, indexing="ij"), -1)


def truth(points: np.ndarray, margin: float, cameras=CAMERAS) -> tuple[np.ndarray, np.ndarray]:
    """Views observing each point (n,) and whether that is robust (n,) bool.

    A camera observes ``c`` iff ``c`` is in front of it, projects into the image and lies no
    deeper than the depth where ITS OWN ray (through ``c``) enters the box plus ``margin``.
    Robust: the same holds for the rays through the four corners of the pixel-sized square
    centred on ``c``'s projection (which holds the centre of the pixel it falls in: the box's
    silhouette is convex and each camera sees one face, at one depth, so the pixel centre's
    ray then agrees too), ``c`` does not project within 0.01 pixel of the image's border, and
    its depth is not within 1e-4 of the margin's end (float32 against float64 rounding).
    """
    count = np.zeros(len(points), np.int64)
    robust = np.ones(len(points), bool)
    for c2w in cameras:
        p = (points - c2w[:3, 3]) @ c2w[:3, :3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = FOCAL * p[:, 0] / z + K[0, 2], FOCAL * p[:, 1] / z + K[1, 2]
        front = z > 0
        inside = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        band = 0.01
        grown = front & (u >= -band) & (u < W + band) & (v >= -band) & (v < H + band)
        shrunk = front & (u >= band) & (u < W - band) & (v >= band) & (v < H - band)
        near_border = grown & ~shrunk
        ok = np.ones(len(points), bool)
        seen = None
        for du, dv in ((0, 0), (0.5, 0.5), (0.5, -0.5), (-0.5, 0.5), (-0.5, -0.5)):
            dirs = np.stack([(u + du - K[0, 2]) / FOCAL, (v + dv - K[1, 2]) / FOCAL, np.ones_like(z)], -1)
            hit = box_depth(c2w, np.nan_to_num(dirs))
            s = inside & (z <= hit + margin)
            if seen is None:
                seen = s
                ok &= ~(np.isfinite(hit) & (np.abs(z - (hit + margin)) < 1e-4))
            else:
                ok &= (s == seen) | ~inside
        count += seen
        robust &= ok & ~near_border
    return count, robust


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Capture:
    return write_box_capture(tmp_path_factory.mktemp("box_capture"))


@pytest.fixture(scope="module")
def grid(capture: Capture) -> VisibilityGrid:
    return build_visibility(capture, BOUNDS, resolution=RES, margin=2.0, full_count=1)


def at(points: list[tuple[float, float, float]]) -> torch.Tensor:
    return torch.tensor(points, dtype=torch.float32)


def count_at(grid: VisibilityGrid, point: tuple[float, float, float]) -> int:
    """The count of the voxel containing ``point``."""
    idx = ((torch.tensor(point) - BOUNDS[0]) / VOXEL).floor().long()
    return int(grid.counts[tuple(idx.tolist())])


# -- the test scene itself -----------------------------------------------------------------------
def test_the_capture_holds_the_exact_depths_of_the_box(capture: Capture) -> None:
    box = Box((BOX_HALF, BOX_HALF, BOX_HALF), (0.0, 0.0, 0.0))
    a = capture.depth(0)
    assert a[H // 2, W // 2] == pytest.approx(0.6, abs=1e-6)  # the z = -0.3 face, 0.6 ahead
    assert (capture.depth(2) == 0).all()  # camera C sees nothing
    # Every hit lies on the box's surface (the analytic SDF is 0 there).
    for i, c2w in enumerate(CAMERAS[:2]):
        d = capture.depth(i).astype(np.float64)
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        cam = np.stack([(u - K[0, 2]) / FOCAL * d, (v - K[1, 2]) / FOCAL * d, d], -1)[d > 0]
        hits = cam @ c2w[:3, :3].T + c2w[:3, 3]
        assert len(hits) > 300
        assert float(box.sdf(torch.from_numpy(hits)).abs().max()) < 1e-5


# -- counts against closed-form truth --------------------------------------------------------------
def test_every_robust_voxel_has_the_closed_form_count(grid: VisibilityGrid) -> None:
    assert grid.resolution == (RES, RES, RES) and grid.counts.dtype == torch.uint8
    assert torch.equal(grid.bounds, BOUNDS) and grid.views == 3
    count, robust = truth(voxel_centres().reshape(-1, 3), margin=2.0 * VOXEL)
    got = grid.counts.reshape(-1).numpy().astype(np.int64)
    assert robust.mean() > 0.9  # left out: voxels whose rays graze a silhouette (4 % per view)
    mismatch = np.flatnonzero(robust & (got != count))
    assert mismatch.size == 0, f"{mismatch.size} voxels differ, e.g. {mismatch[:5]}"
    # Non-trivial: voxels seen by none, one and two cameras (C's frustum, beyond the box, is
    # hidden from A or outside B's).
    assert set(np.unique(count[robust]).tolist()) == {0, 1, 2}
    # Elsewhere the pixel-centre depth may differ from the depth along the voxel's own ray;
    # that changes few counts (108 of 64000 here), each by one view.
    assert (got != count).mean() < 0.005 and np.abs(got - count).max() <= 1


def test_hand_counted_points(grid: VisibilityGrid) -> None:
    """Voxel centres whose views are counted by hand (a camera sees |x|, |y| <= 0.6 z)."""
    cases = {
        # A: z 0.575, |x| 0.325 <= 0.345; B: depth 0.575, |z| 0.325 <= 0.345; both in front
        # of the faces they see, C behind it: 2.
        (-0.325, 0.025, -0.325): 2,
        # A: 0.325 ahead on its axis; B: depth 0.925, |z| 0.575 > 0.555: 1.
        (0.025, 0.025, -0.575): 1,
        # B: 0.325 ahead on its axis; A: depth 0.925, |x| 0.575 > 0.555: 1.
        (-0.575, 0.025, 0.025): 1,
        # Behind the box for both A and B (their rays enter it on its near faces), behind C: 0.
        (0.625, 0.025, 0.625): 0,
        # Inside the box, 0.3 behind both faces (margin 0.1): 0.
        (0.025, 0.025, 0.025): 0,
        # In front of A but outside its frustum (|x| 0.925 > 0.6 * 0.375), behind B and C: 0.
        (-0.925, 0.025, -0.525): 0,
        # Behind every camera: 0.
        (-0.925, 0.025, -0.925): 0,
        # C's last voxel before the bounds: its pixel has no hit, so C sees up to the bounds;
        # A's ray to it enters the box's front face first; B: |z| 0.975 > 0.6 * 1.425: 1.
        (0.525, -0.475, 0.975): 1,
    }
    for point, views in cases.items():
        assert count_at(grid, point) == views, point
    # full_count = 1: the weight of a voxel centre seen by one view or more is 1.
    w = grid.observed(at(list(cases)))
    assert w.tolist() == [float(v > 0) for v in cases.values()]


def test_every_view_counts_once(tmp_path: Path) -> None:
    """A taken three times and B once: a voxel seen by all of them counts 4, by A alone 3."""
    cap = write_box_capture(tmp_path, cameras=(CAM_A, CAM_A, CAM_B, CAM_A))
    g = build_visibility(cap, BOUNDS, resolution=RES)
    assert g.views == 4
    assert count_at(g, (-0.325, 0.025, -0.325)) == 4
    assert count_at(g, (0.025, 0.025, -0.575)) == 3
    assert count_at(g, (-0.575, 0.025, 0.025)) == 1
    assert count_at(g, (0.625, 0.025, 0.625)) == 0
    # full_count 2 (the default): one view is half an observation.
    w = g.observed(at([(-0.325, 0.025, -0.325), (-0.575, 0.025, 0.025)]))
    assert w.tolist() == [1.0, 0.5]


@pytest.mark.parametrize(("margin", "layers"), [(0.0, 0), (2.0, 2), (4.0, 4)])
def test_margin_behind_the_surface(capture: Capture, margin: float, layers: int) -> None:
    """On A's axis the face is at z = -0.3; voxel layers behind it (centres -0.275, -0.225,
    ...) are observed up to ``margin`` voxels deep, by A alone (B's rays enter the box first)."""
    g = build_visibility(capture, BOUNDS, resolution=RES, margin=margin, full_count=1)
    column = [count_at(g, (0.025, 0.025, -0.325 + VOXEL * k)) for k in range(7)]
    assert column == [1] + [1] * layers + [0] * (6 - layers)
    assert g.margin == margin


def test_observed_is_one_in_front_of_the_surface_and_zero_behind(grid: VisibilityGrid) -> None:
    on_face = at([(0.0, 0.0, -0.3), (0.1, -0.1, -0.3), (-0.3, 0.1, 0.0)])
    assert grid.observed(on_face).tolist() == [1.0, 1.0, 1.0]
    behind = at([(0.0, 0.0, -0.05), (0.05, 0.1, 0.2), (0.0, 0.0, 0.6)])
    assert grid.observed(behind).tolist() == [0.0, 0.0, 0.0]


def test_no_hit_pixels_observe_up_to_the_bounds(tmp_path: Path) -> None:
    cap = write_box_capture(tmp_path, cameras=(CAM_C,))
    g = build_visibility(cap, BOUNDS, resolution=RES, full_count=1)
    count, robust = truth(voxel_centres().reshape(-1, 3), margin=0.0, cameras=(CAM_C,))
    got = g.counts.reshape(-1).numpy()
    assert (got[robust] == count[robust]).all()
    # The frustum's last voxel layer (z centre 0.975) is observed; beyond the bounds nothing.
    assert count_at(g, (0.525, -0.475, 0.975)) == 1
    near_far_face = at([(0.5, -0.5, 0.99), (0.5, -0.5, 1.0)])
    assert g.observed(near_far_face).tolist() == [1.0, 1.0]
    assert g.observed(at([(0.5, -0.5, 1.001), (0.5, -0.5, 0.69)])).tolist() == [0.0, 0.0]


def test_a_coarser_pixel_stride_never_observes_more(capture: Capture, grid: VisibilityGrid) -> None:
    """A 5 x 5 block takes its nearest hit: less is observed, but never more, and nothing
    changes where every view sees the voxel in front of all its hits (each view's nearest hit
    is at depth 0.6: z <= -0.2 for A, x <= -0.2 for B, and C has none)."""
    coarse = build_visibility(capture, BOUNDS, resolution=RES, margin=2.0, pixel_stride=5)
    assert coarse.pixel_stride == 5
    assert bool((coarse.counts <= grid.counts).all())
    assert int(coarse.counts.sum()) < int(grid.counts.sum())  # A's and B's rims are lost
    front = torch.from_numpy((voxel_centres()[..., 0] <= -0.2) & (voxel_centres()[..., 2] <= -0.2))
    assert torch.equal(coarse.counts[front], grid.counts[front])
    assert int(grid.counts[front].sum()) > 200


def test_frames_without_depth_contribute_nothing(tmp_path: Path) -> None:
    cap = write_box_capture(tmp_path, with_depth=False)
    with pytest.raises(CaptureError, match="none of the 3 frames has depth"):
        build_visibility(cap, BOUNDS, resolution=8)
    with pytest.raises(CaptureError, match="no training frames"):
        build_visibility(cap, BOUNDS, resolution=8, indices=[])


def test_bad_arguments_are_refused(capture: Capture) -> None:
    for kwargs, match in [({"resolution": 0}, "resolution"), ({"pixel_stride": 0}, "pixel_stride"),
                          ({"margin": -1.0}, "margin"), ({"full_count": 0}, "full_count")]:
        with pytest.raises(ValueError, match=match):
            build_visibility(capture, BOUNDS, **{"resolution": 8, **kwargs})
    with pytest.raises(ValueError, match="bounds"):
        build_visibility(capture, torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]]), resolution=8)


def test_the_grid_follows_the_bounds_aspect_and_frame(capture: Capture) -> None:
    """A box 2 x 1 x 0.5 gets 32 x 16 x 8 voxels; points are in the normalised frame."""
    bounds = torch.tensor([[-1.0, -0.5, -0.75], [1.0, 0.5, -0.25]])
    g = build_visibility(capture, bounds, resolution=32, full_count=1)
    assert g.resolution == (32, 16, 8)
    # In front of A's face (normalised z -0.5); the same point in metres is far outside.
    assert g.observed(at([(0.0, 0.0, -0.5)])).item() == 1.0
    metres = torch.tensor([[0.0, 0.0, -0.5]], dtype=torch.float64) * WORLD_SCALE + torch.from_numpy(WORLD_OFFSET)
    assert g.observed(metres.float()).item() == 0.0


# -- observed(): the weight ------------------------------------------------------------------------
def test_observed_interpolates_the_saturated_count_and_is_zero_outside() -> None:
    """Two voxels along x over [0, 2] x [0, 1] x [0, 1], seen by 3 and 0 views."""
    g = VisibilityGrid(torch.tensor([3, 0], dtype=torch.uint8).view(2, 1, 1),
                       torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), full_count=2)
    x = at([(0.5, 0.5, 0.5), (1.0, 0.5, 0.5), (1.25, 0.5, 0.5), (1.5, 0.5, 0.5),
            (0.1, 0.0, 1.0), (-0.01, 0.5, 0.5), (0.5, 0.5, 1.01), (float("nan"), 0.5, 0.5)])
    w = g.observed(x)
    assert w.dtype == torch.float32 and w.shape == (8,)
    # Centres: min(3, 2) / 2 = 1 and 0; linear between; the border half-voxel takes the
    # outermost value; outside the bounds and NaN: 0.
    assert w.tolist() == [1.0, 0.5, 0.25, 0.0, 1.0, 0.0, 0.0, 0.0]
    assert g.observed(x, full_count=3).tolist()[:2] == [1.0, 0.5]
    assert g.observed(x, full_count=6).tolist()[0] == 0.5
    assert g.observed(torch.zeros(0, 3)).shape == (0,)
    big = torch.rand(3_000_000, 3) * torch.tensor([2.0, 1.0, 1.0])  # several lookup chunks
    w_big = g.observed(big)
    np.testing.assert_allclose(w_big.numpy(), np.clip(1.5 - big[:, 0].numpy(), 0, 1), atol=1e-5)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        g.observed(torch.zeros(4, 2))


def test_metadata_round_trip_and_strict_parsing() -> None:
    counts = torch.randint(0, 256, (4, 3, 2), dtype=torch.uint8)
    g = VisibilityGrid(counts, BOUNDS, margin=1.5, full_count=3, pixel_stride=2, views=7)
    meta = json.loads(json.dumps(g.to_json()))
    assert meta == {"resolution": [4, 3, 2], "bounds": BOUNDS.tolist(), "margin": 1.5,
                    "full_count": 3, "pixel_stride": 2, "views": 7}
    back = VisibilityGrid.from_json(meta, counts.clone())
    assert torch.equal(back.counts, counts) and back.to_json() == meta
    for change, match in [({"resolution": [4, 3, True]}, "integer"), ({"margin": float("inf")}, "margin"),
                          ({"full_count": 256}, "full_count"), ({"bounds": [[0, 0, 0], [0, 1, 1]]}, "bounds"),
                          ({"extra": 1}, "unknown keys"), ({"views": 1.0}, "views")]:
        with pytest.raises(ValueError, match=match):
            VisibilityGrid.parse_json({**meta, **change})
    with pytest.raises(ValueError, match="missing keys"):
        VisibilityGrid.parse_json({k: v for k, v in meta.items() if k != "margin"})
    with pytest.raises(ValueError, match="resolution"):
        VisibilityGrid.from_json({**meta, "resolution": [4, 3, 3]}, counts)
    with pytest.raises(ValueError, match="uint8"):
        VisibilityGrid(counts.int(), BOUNDS)


@pytest.mark.cuda
def test_build_and_lookup_on_the_device_agree_with_cpu(capture: Capture, grid: VisibilityGrid, device: str) -> None:
    g = build_visibility(capture, BOUNDS.to(device), resolution=RES, margin=2.0, full_count=1, device=device)
    assert g.counts.device.type == torch.device(device).type and torch.equal(g.counts.cpu(), grid.counts)
    x = BOUNDS[0] + torch.rand(10_000, 3) * 2.0
    # The same counts, interpolated in float32 on either device: equal to rounding (measured on
    # an H200: 1.9e-6 at most).
    torch.testing.assert_close(g.observed(x.to(device)).cpu(), grid.observed(x), atol=1e-5, rtol=0)
    assert grid.to(device).observed(x.to(device)).device.type == torch.device(device).type


# -- fields and checkpoints ------------------------------------------------------------------------
TINY = NeuralSDFConfig(levels=2, finest_resolution=16, hidden_dim=16, base_resolution=8,
                       geo_feature_dim=3, color_hidden_dim=8)


def tiny_field(with_grid: bool = True) -> NeuralSDF:
    torch.manual_seed(0)
    to_world = torch.from_numpy(WORLDTOGT.copy())
    field = NeuralSDF(TINY, bounds=torch.tensor([[-0.9, -0.5, -0.3], [0.8, 0.6, 0.95]]),
                      to_world=to_world, info=FieldInfo(label="chair", name="c"))
    if with_grid:
        g = torch.Generator().manual_seed(1)
        counts = torch.randint(0, 256, (17, 11, 13), generator=g, dtype=torch.uint8)
        field.visibility = VisibilityGrid(counts, field.bounds, margin=2.0, full_count=2, views=9)
    return field


def stored(path: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    with safe_open(str(path), framework="pt") as f:
        header = json.loads(f.metadata()[HEADER_KEY])
    return header, load_file(str(path))


def forge(path: Path, header: dict, tensors: dict[str, torch.Tensor]) -> Path:
    """Rewrite a checkpoint with a correct digest (as a forger, or an older regnf, writes it)."""
    header = {**header, DIGEST_KEY: content_digest({k: v for k, v in header.items() if k != DIGEST_KEY}, tensors)}
    save_file(tensors, str(path), metadata={HEADER_KEY: json.dumps(header)})
    return path


def test_analytic_and_new_fields_have_no_grid() -> None:
    assert Box((0.1, 0.1, 0.1)).visibility is None
    assert tiny_field(with_grid=False).visibility is None


def test_a_grid_is_part_of_the_field() -> None:
    field = tiny_field()
    assert VISIBILITY_TENSOR in field.state_dict()
    assert field.state_dict()[VISIBILITY_TENSOR].dtype == torch.uint8
    field.double()  # a dtype cast leaves integer counts alone; lookups still work
    assert field.visibility.counts.dtype == torch.uint8
    assert field.visibility.observed(torch.zeros(2, 3, dtype=torch.float64)).dtype == torch.float32
    field.visibility = None
    assert VISIBILITY_TENSOR not in field.state_dict()


def test_checkpoint_round_trip_keeps_the_grid_bit_exact(tmp_path: Path) -> None:
    field = tiny_field()
    path = save_field(field, tmp_path / "f.safetensors")
    header, tensors = stored(path)
    assert header[VISIBILITY_KEY] == field.visibility.to_json()
    assert tensors[VISIBILITY_TENSOR].dtype == torch.uint8
    assert verify_checkpoint(path) == header
    loaded = load_field(path)
    g, h = field.visibility, loaded.visibility
    assert isinstance(h, VisibilityGrid)
    assert torch.equal(h.counts, g.counts) and torch.equal(h.bounds, g.bounds)
    assert h.to_json() == g.to_json()
    x = field.bounds[0] + torch.rand(2000, 3) * (field.bounds[1] - field.bounds[0])
    assert torch.equal(h.observed(x), g.observed(x))
    # Without a grid the header says so (null) and no tensor is stored.
    plain = save_field(tiny_field(with_grid=False), tmp_path / "plain.safetensors")
    assert read_header(plain)[VISIBILITY_KEY] is None
    assert VISIBILITY_TENSOR not in stored(plain)[1]
    assert load_field(plain).visibility is None


def test_a_flipped_bit_in_the_counts_fails_the_digest(tmp_path: Path) -> None:
    path = save_field(tiny_field(), tmp_path / "f.safetensors")
    data = bytearray(path.read_bytes())
    n = int.from_bytes(data[:8], "little")
    start = json.loads(data[8 : 8 + n])[VISIBILITY_TENSOR]["data_offsets"][0]
    data[8 + n + start + 100] ^= 0x01
    path.write_bytes(bytes(data))
    for fn in (load_field, verify_checkpoint):
        with pytest.raises(CheckpointError, match="content digest mismatch"):
            fn(path)


@pytest.mark.parametrize("how", ["absent", "null"])
def test_a_checkpoint_without_a_grid_loads_with_none(tmp_path: Path, how: str) -> None:
    """Format-2 files written before grids existed have no 'visibility' key at all."""
    path = save_field(tiny_field(with_grid=False), tmp_path / "f.safetensors")
    header, tensors = stored(path)
    if how == "absent":
        del header[VISIBILITY_KEY]
        forge(path, header, tensors)
    assert verify_checkpoint(path)["format_version"] == 2
    field = load_field(path)
    assert field.visibility is None
    assert torch.equal(field.state_dict()["sdf_layers.0.weight"], tensors["sdf_layers.0.weight"])


def _edited(path: Path, edit_header=None, edit_tensors=None) -> Path:
    header, tensors = stored(path)
    if edit_header:
        edit_header(header)
    if edit_tensors:
        edit_tensors(tensors)
    return forge(path, header, tensors)


@pytest.mark.parametrize(
    ("edit_header", "edit_tensors", "match"),
    [
        (lambda h: h[VISIBILITY_KEY].update(resolution=[17, 11, 12]), None,
         r"'visibility.counts' has shape \(17, 11, 13\), (expected|the header's visibility resolution)"),
        (None, lambda t: t.update({VISIBILITY_TENSOR: t[VISIBILITY_TENSOR].to(torch.int16)}), "dtype"),
        (lambda h: h[VISIBILITY_KEY].update(bounds=[[0, 0, 0], [1, 1, float("nan")]]), None,
         "bad 'visibility' block: 'bounds'"),
        (lambda h: h[VISIBILITY_KEY].update(resolution=[17, 11, "13"]), None, "bad 'visibility' block"),
        (lambda h: h.update({VISIBILITY_KEY: [1, 2]}), None, "bad 'visibility' block: must be an object"),
        (None, lambda t: t.pop(VISIBILITY_TENSOR), r"missing tensors \['visibility.counts'\]"),
        (lambda h: h.update({VISIBILITY_KEY: None}), None, r"unexpected tensors \['visibility.counts'\]"),
    ],
    ids=["shape", "dtype", "nan-bounds", "string-resolution", "not-an-object", "missing", "unexpected"],
)
def test_a_grid_that_disagrees_with_its_header_is_refused(tmp_path: Path, edit_header, edit_tensors, match: str) -> None:
    path = _edited(save_field(tiny_field(), tmp_path / "f.safetensors"), edit_header, edit_tensors)
    for fn in (load_field, verify_checkpoint):
        with pytest.raises(CheckpointError, match=match) as info:
            fn(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_huge_grid_is_refused_from_the_header_before_anything_is_read(tmp_path: Path) -> None:
    path = _edited(save_field(tiny_field(), tmp_path / "f.safetensors"),
                   lambda h: h[VISIBILITY_KEY].update(resolution=[100_000, 100_000, 100_000]))
    for fn in (read_header, verify_checkpoint, load_field):
        start = time.perf_counter()
        with pytest.raises(CheckpointError, match=r"100000 voxels along x exceed the limit 1024"):
            fn(path)
        assert time.perf_counter() - start < 0.5
    path = _edited(path, lambda h: h[VISIBILITY_KEY].update(resolution=[1024, 1024, 1024]))
    with pytest.raises(CheckpointError, match="exceed the limit 67108864"):
        read_header(path)
    # The limits are a parameter, as the architecture's are.
    with pytest.raises(CheckpointError, match="max_visibility_voxels"):
        read_header(save_field(tiny_field(), tmp_path / "g.safetensors"),
                    limits=ArchitectureLimits(max_visibility_voxels=1000))


def test_attach_visibility_adds_the_grid_of_the_capture(tmp_path: Path, capture: Capture) -> None:
    field = tiny_field(with_grid=False)
    src = save_field(field, tmp_path / "f.safetensors")
    before = src.read_bytes()
    out = attach_visibility(src, capture, tmp_path / "with.safetensors", resolution=24)
    assert src.read_bytes() == before  # out_path given: the original is left alone
    loaded = load_field(out)
    want = build_visibility(capture, field.bounds, resolution=24)
    assert torch.equal(loaded.visibility.counts, want.counts)
    assert loaded.visibility.to_json() == want.to_json()
    a, b = field.state_dict(), loaded.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert read_header(out)["provenance"] == read_header(src)["provenance"]
    attach_visibility(src, capture, resolution=24)  # in place
    assert torch.equal(load_field(src).visibility.counts, want.counts)
    # A field from another frame cannot take its grid from this capture.
    other = tiny_field(with_grid=False)
    other.to_world[:3, 3] += 1.0
    with pytest.raises(CheckpointError, match="does not live in this capture's normalised frame"):
        attach_visibility(save_field(other, tmp_path / "o.safetensors"), capture)


# -- the cache keeps old fields and adds their grid --------------------------------------------------
CONFIG = RGBDTrainConfig(steps=2, batch_surface=256, batch_free=128, batch_empty=128,
                         batch_eikonal=64, architecture=TINY, visibility_resolution=24)


@pytest.mark.parametrize("how", ["absent", "null"])
def test_the_cache_adds_the_grid_to_an_old_entry_without_retraining(
    tmp_path: Path, capture: Capture, monkeypatch: pytest.MonkeyPatch, how: str
) -> None:
    cache = Cache(tmp_path / "cache", progress=False)
    path = cache.rgbd_field(capture, CONFIG)
    trained = load_field(path)
    assert trained.visibility is not None and trained.visibility.views == 3
    # The entry as regnf wrote it before fields recorded visibility: no grid, no tensor.
    header, tensors = stored(path)
    tensors.pop(VISIBILITY_TENSOR)
    if how == "absent":
        del header[VISIBILITY_KEY]
    else:
        header[VISIBILITY_KEY] = None
    forge(path, header, tensors)
    assert load_field(path).visibility is None

    def no_training(*args, **kwargs):
        raise AssertionError("the cache retrained a field it only had to add a grid to")

    monkeypatch.setattr(cache_module, "train_rgbd", no_training)
    assert cache.rgbd_field(capture, CONFIG) == path
    upgraded = load_field(path)
    assert torch.equal(upgraded.visibility.counts, trained.visibility.counts)  # what training made
    assert upgraded.visibility.to_json() == trained.visibility.to_json()
    a, b = trained.state_dict(), upgraded.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    new_header = verify_checkpoint(path)
    assert new_header["provenance"] == header["provenance"]
    _, fingerprint = cache.rgbd_entry(capture, CONFIG)
    assert reusable(path, {"data_sha256": fingerprint})
    # Reused as is from now on: not rewritten again.
    stamp = (path.read_bytes(), os.stat(path).st_mtime_ns)
    assert cache.rgbd_field(capture, CONFIG) == path
    assert (path.read_bytes(), os.stat(path).st_mtime_ns) == stamp
    leftovers = [p.name for p in path.parent.iterdir() if p != path]
    assert leftovers == []  # re-saved atomically: no temporary file left


def test_the_cache_leaves_an_entry_alone_when_the_config_asks_for_no_grid(
    tmp_path: Path, capture: Capture, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = dataclasses.replace(CONFIG, visibility_resolution=0)
    cache = Cache(tmp_path / "cache", progress=False)
    path = cache.rgbd_field(capture, config)
    assert load_field(path).visibility is None
    before = path.read_bytes()
    monkeypatch.setattr(cache_module, "attach_visibility", lambda *a, **k: pytest.fail("attached"))
    assert cache.rgbd_field(capture, config) == path and path.read_bytes() == before
