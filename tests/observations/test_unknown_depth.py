"""Depth as sensors write it: a pixel without depth is free space only in regnf's ideal renders.

The scene is a sphere in front of a wall (closed-form ray intersections in numpy), seen by one
camera; a block of pixels on the sphere loses its depth (0, as a sensor without a return writes
it). The truth is the scene itself: the dropped rays do hit the sphere, so where zeros are
unknown no free-space sample, edge ray or observed voxel may come from them; where zeros are
empty (regnf's own ideal renders) the old behaviour holds.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from regnf.captures.model import Capture, CaptureError
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.observations.rgbd_samples import build_samples, edge_depths, outline_pixels
from regnf.observations.visibility import build_visibility
from regnf.training.training import _ViewStack

W = H = 32
FOCAL = 30.0
K = np.array([[FOCAL, 0.0, W / 2], [0.0, FOCAL, H / 2], [0.0, 0.0, 1.0]])
EYE = np.array([0.0, 0.0, 2.5])
C2W = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera looking down -z, y down
C2W[:3, 3] = EYE
SPHERE_R = 0.5
WALL_Z = -0.8
HOLE = (slice(12, 20), slice(12, 20))
"""Pixels on the sphere whose depth is dropped."""
RES = 16


def pixel_dirs() -> np.ndarray:
    """(H, W, 3) world rays through the pixel centres with camera z component 1."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    cam = np.stack([(u - K[0, 2]) / FOCAL, (v - K[1, 2]) / FOCAL, np.ones_like(u)], -1)
    return cam @ C2W[:3, :3].T


def true_depth() -> np.ndarray:
    """(H, W) z-depth of the nearest of the sphere (at the origin) and the wall z = WALL_Z."""
    d = pixel_dirs()
    b = (d * EYE).sum(-1)
    a = (d * d).sum(-1)
    disc = b * b - a * (EYE @ EYE - SPHERE_R**2)
    t_sphere = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
    t_wall = (WALL_Z - EYE[2]) / d[..., 2]
    return np.minimum(t_sphere, t_wall)  # the camera z component is 1: t is z-depth


def write(root: Path, depth: np.ndarray, meta: dict | None) -> Capture:
    rgb = np.full((H, W, 3), 128, np.uint8)
    write_capture(root, [rgb], [depth], C2W[None], K, np.eye(4), meta=meta)
    return load_capture(root)


def dropped() -> np.ndarray:
    depth = true_depth()
    depth[HOLE] = 0.0
    return depth


@pytest.fixture(params=["unknown", "empty"])
def capture(request: pytest.FixtureRequest, tmp_path: Path) -> Capture:
    return write(tmp_path, dropped(), {"zero_depth": request.param})


def hole_dirs() -> np.ndarray:
    d = pixel_dirs()[HOLE].reshape(-1, 3)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def on_hole_rays(dirs: torch.Tensor) -> np.ndarray:
    """(n,) bool: the unit direction is one of the dropped pixels' rays."""
    if dirs.shape[0] == 0:
        return np.zeros(0, bool)
    return (dirs.double().numpy() @ hole_dirs().T > 1.0 - 1e-5).any(-1)  # float32 rays; neighbours are 1e-3 apart


def test_the_meaning_of_zero_follows_the_capture(tmp_path: Path) -> None:
    cases = {
        "real": (None, False),
        "regnf": ({"generator": "regnf.synthetic/2"}, True),
        "noisy": ({"generator": "regnf.synthetic/2", "noise": {"level": "sensor", "seed": 0}}, False),
        "override": ({"generator": "regnf.synthetic/2", "zero_depth": "unknown"}, False),
    }
    for name, (meta, empty) in cases.items():
        assert write(tmp_path / name, true_depth().clip(max=10.0), meta).zero_depth_is_empty is empty, name


def test_unknown_depth_gives_no_free_space_samples(capture: Capture) -> None:
    s = build_samples(capture, [0])
    if capture.zero_depth_is_empty:
        # Every dropped pixel (and nothing else: the wall fills the view) is a free ray.
        assert s.free_dirs.shape[0] == 64
        assert on_hole_rays(s.free_dirs).sum() == 64
        assert on_hole_rays(s.edge_dirs).any()
    else:
        assert s.free_dirs.shape[0] == 0 and s.free_origins.shape[0] == 0
        assert not on_hole_rays(s.edge_dirs).any()
    # No surface point on a dropped ray either way.
    assert not on_hole_rays((s.points - s.origins) / s.ray_t[:, None]).any()
    assert s.points.shape[0] == W * H - 64


def test_unknown_depth_is_never_seen_free(capture: Capture) -> None:
    views = _ViewStack.build(capture, [0], torch.device("cpu"))
    # Points along the dropped rays before and behind the true surface (the sphere).
    t = true_depth()[HOLE].reshape(-1, 1)
    rays = pixel_dirs()[HOLE].reshape(-1, 3)
    pts = np.concatenate([EYE + rays * (0.5 * t), EYE + rays * (t + 0.2)])
    free = views.seen_free(torch.from_numpy(pts).float(), 0.01, torch.zeros(len(pts), dtype=torch.long))
    assert bool((free == (1.0 if capture.zero_depth_is_empty else 0.0)).all())


def test_unknown_depth_observes_no_voxel(capture: Capture) -> None:
    bounds = torch.tensor([[-1.0] * 3, [1.0] * 3])
    grid = build_visibility(capture, bounds, resolution=RES)
    centres = (np.stack(np.meshgrid(*[np.arange(RES) + 0.5] * 3, indexing="ij"), -1) / RES) * 2.0 - 1.0
    # Closed-form projection of every voxel centre into the camera.
    pc = (centres - EYE) @ C2W[:3, :3]
    u = FOCAL * pc[..., 0] / pc[..., 2] + K[0, 2]
    v = FOCAL * pc[..., 1] / pc[..., 2] + K[1, 2]
    # Strictly inside the hole (a pixel of slack for rounding).
    inner = (u > 13) & (u < 19) & (v > 13) & (v < 19)
    behind = pc[..., 2] > true_depth()[16, 16] + 0.3
    counts = grid.counts.numpy()
    assert inner.sum() > 20 and (inner & behind).sum() > 5
    if capture.zero_depth_is_empty:
        assert (counts[inner] == 1).all()  # a ray that hit nothing observes up to the bounds
    else:
        assert (counts[inner] == 0).all()


def test_an_unknown_neighbour_makes_no_edge_and_no_outline() -> None:
    depth = np.full((5, 7), 2.0)
    depth[2, 3] = 0.0  # a dropout in a flat wall
    depth[:, 6] = 4.0  # a real step to a farther surface
    valid = depth > 0
    k = np.array([[100.0, 0, 3.5], [0, 100.0, 2.5], [0, 0, 1]])
    edge_unknown = edge_depths(depth, valid, k, zeros_empty=False)
    outline_unknown = outline_pixels(depth, valid, k, zeros_empty=False)
    assert edge_unknown[2, 3] == 0.0
    assert not outline_unknown[1:4, 2:5].any()
    # The real step still makes its edge and its outline.
    assert (edge_unknown[:, 6] == 2.0).all() and outline_unknown[:, 5].all()
    # With zeros empty the dropout is a hole: an edge on it, an outline around it.
    assert edge_depths(depth, valid, k)[2, 3] == 2.0
    outline_empty = outline_pixels(depth, valid, k)
    assert outline_empty[1, 3] and outline_empty[3, 3] and outline_empty[2, 2] and outline_empty[2, 4]


def test_nan_depth_is_unknown_where_zeros_are_and_refused_elsewhere(tmp_path: Path) -> None:
    nan = dropped()
    nan[HOLE] = np.nan
    unknown = write(tmp_path / "u", nan, None)
    assert np.array_equal(unknown.depth(0), dropped().astype(np.float32))
    empty = write(tmp_path / "e", nan, {"zero_depth": "empty"})
    with pytest.raises(CaptureError, match=r"frame 0: depth has 64 non-finite values"):
        empty.depth(0)


def test_a_bad_override_is_refused_at_load(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match=r"meta_data.json: regnf.zero_depth must be 'empty' or 'unknown', got 'none'"):
        write(tmp_path, true_depth(), {"zero_depth": "none"})


def test_a_capture_whose_zeros_are_unknown_gets_its_own_cache_key(tmp_path: Path) -> None:
    """A field trained when zeros were taken as empty is never reused for a capture whose zeros are
    unknown; a capture whose zeros are empty keeps the key it always had."""
    from regnf.synthetic.cache import Cache, config_key
    from regnf.training.presets import object_rgbd_preset
    from regnf.training.training import TRAIN_VERSION
    from tests.observations.capture_helpers import write_analytic_capture

    empty = write_analytic_capture(tmp_path / "a")
    meta = json.loads((tmp_path / "a" / "meta_data.json").read_text())
    meta["regnf"]["zero_depth"] = "unknown"
    unknown_dir = tmp_path / "b"
    shutil.copytree(tmp_path / "a", unknown_dir)
    (unknown_dir / "meta_data.json").write_text(json.dumps(meta))
    unknown = load_capture(unknown_dir)
    assert empty.zero_depth_is_empty and not unknown.zero_depth_is_empty
    cache, cfg = Cache(tmp_path / "cache"), object_rgbd_preset()
    path_empty, fingerprint = cache.rgbd_entry(empty, cfg)
    assert path_empty.name.endswith(f"-rgbd-{config_key(cfg, fingerprint, TRAIN_VERSION)}.safetensors")
    path_unknown, fingerprint_unknown = cache.rgbd_entry(unknown, cfg)
    assert fingerprint_unknown != fingerprint  # the metadata differs: the key already differs by its bytes
    assert path_unknown.name != path_empty.name
    assert not path_unknown.name.endswith(f"-rgbd-{config_key(cfg, fingerprint_unknown, TRAIN_VERSION)}.safetensors")
