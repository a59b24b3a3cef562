"""A field trained from each reader's capture agrees with one trained from an sdfstudio copy of
the same frames: max |SDF difference| in metres, at points of the room's surface that the frames
see, below 0.1 % of the room's diagonal.

The ScanNet and nerfstudio folders are written by test code (``scannet_helpers``,
``ns_helpers``); the sdfstudio copy holds the same frames' analytic poses (metres), the same
millimetre depth and the same colour, with the reader's ``worldtogt`` so that both trainings
run in the same normalised frame. Training is deterministic on the CPU, so the two fields differ
only as far as the data the readers give differs: a pose off by a centimetre moves the fields
apart by centimetres at these steps, far beyond the bar.
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from regnf.captures.formats import read_capture
from regnf.captures.model import Capture
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.fields.field import Field
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.render.evaluation import world_to_field
from regnf.training.training import RGBDTrainConfig, train_rgbd
from tests.captures import ns_helpers, scannet_helpers

CONFIG = RGBDTrainConfig(
    steps=60, batch_surface=1024, batch_free=512, batch_empty=512, batch_eikonal=256, visibility_resolution=16,
    architecture=NeuralSDFConfig(levels=4, features_per_level=2, base_resolution=16, finest_resolution=48,
                                 hidden_dim=32, color_hidden_dim=32, inside_out=True, init_radius=0.9),
)
"""A tiny room field: a few seconds on 2 cores."""

BAR = 1e-3
"""Largest SDF difference, as a fraction of the room's diagonal."""


def _surface_points(poses: np.ndarray, depth_m: list[np.ndarray], K: np.ndarray, per_frame: int = 300) -> np.ndarray:
    """(n, 3) points of the room's surface seen by the frames, metres (exact depth back-projected)."""
    rng = np.random.default_rng(0)
    out = []
    for pose, z in zip(poses, depth_m, strict=True):
        v, u = np.mgrid[0 : z.shape[0], 0 : z.shape[1]] + 0.5
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1).reshape(-1, 3)
        pick = rng.choice(len(cam), per_frame, replace=False)
        out.append(cam[pick] @ pose[:3, :3].T + pose[:3, 3])
    return np.concatenate(out)


def _sdf_metres(field: Field, points: np.ndarray) -> np.ndarray:
    return field.sdf_chunked(world_to_field(field, points)).double().numpy() * field.world_scale


def _assert_fields_agree(capture: Capture, copy: Capture, points: np.ndarray, diag: float) -> None:
    # Reader data is compared, not pose refinement (on for estimated poses): off in both.
    capture.poses_estimated = copy.poses_estimated = False
    a, _ = train_rgbd(capture, CONFIG, progress=False)
    b, _ = train_rgbd(copy, CONFIG, progress=False)
    diff = np.abs(_sdf_metres(a, points) - _sdf_metres(b, points))
    assert diff.max() < BAR * diag, f"max |SDF difference| {diff.max() * 1e3:.2f} mm > {BAR * diag * 1e3:.2f} mm"


def test_scannet_field_agrees_with_the_sdfstudio_copy(tmp_path: Path) -> None:
    """Colour on the depth grid in the copy is the reader's resampling (checked against the
    analytic wall colours in test_scannet.py); poses, depth and intrinsics are the truth's."""
    h = scannet_helpers
    poses = h.write_scannet(tmp_path / "scannet")
    capture, _ = read_capture(tmp_path / "scannet")
    ids = [int(f.rgb_path.stem) for f in capture.frames]
    rgb = [np.round(capture.rgb(i) * 255.0).astype(np.uint8) for i in range(len(ids))]
    depth = [h.depth_mm(poses[k]).astype(np.float64) / 1000.0 for k in ids]
    write_capture(tmp_path / "sdf", rgb, depth, poses[ids], h.K_DEPTH, capture.worldtogt,
                  meta={"zero_depth": "unknown"})
    points = _surface_points(poses[ids], [h.true_depth(poses[k]) for k in ids], h.K_DEPTH)
    _assert_fields_agree(capture, load_capture(tmp_path / "sdf"), points, h.DIAG)


def test_nerfstudio_field_agrees_with_the_sdfstudio_copy(tmp_path: Path) -> None:
    h = ns_helpers
    h.write_nerfstudio(tmp_path / "ns")
    capture, _ = read_capture(tmp_path / "ns")
    poses = h.truth_poses()
    rgb = [iio.imread(tmp_path / "ns" / "images" / f"frame_{i:05d}.png") for i in range(len(poses))]
    depth = [iio.imread(tmp_path / "ns" / "depth" / f"frame_{i:05d}.png").astype(np.float64) / 1000.0
             for i in range(len(poses))]
    K = np.array([[h.FX, 0.0, h.CX], [0.0, h.FY, h.CY], [0.0, 0.0, 1.0]])
    write_capture(tmp_path / "sdf", rgb, depth, poses, K, capture.worldtogt, meta={"zero_depth": "unknown"})
    points = _surface_points(poses, [h.true_depth(p) for p in poses], K)
    diag = float(np.linalg.norm(h.ROOM[1] - h.ROOM[0]))
    _assert_fields_agree(capture, load_capture(tmp_path / "sdf"), points, diag)
