"""A distorted nerfstudio capture of the analytic room: its depth back-projects onto the walls.

Test code writes the room (:mod:`tests.captures.ns_helpers`) as a camera with lens distortion
sees it: each pixel's true ray comes from inverting the distortion HERE (fixed-point iteration
for OPENCV, bisection for the fisheye, both independent of :mod:`regnf.captures.distortion`),
its z-depth is the exact ray-box exit, stored as a 16-bit millimetre PNG.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.captures.formats import read_capture
from regnf.captures.model import Capture
from regnf.observations.rgbd_samples import build_samples
from tests.captures.ns_helpers import CX, CY, FX, FY, ROOM, H, W, truth_poses, write_nerfstudio

LENSES = {
    "OPENCV": {"k1": -0.28, "k2": 0.07, "p1": 1e-3, "p2": -5e-4},
    "OPENCV_FISHEYE": {"k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.0005},
}
"""Realistic coefficients per camera model."""


def forward(model: str, c: dict, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lens (OpenCV's documented formulas) on undistorted normalised coordinates."""
    if model == "OPENCV":
        r2 = x * x + y * y
        radial = 1 + c["k1"] * r2 + c["k2"] * r2**2
        return (x * radial + 2 * c["p1"] * x * y + c["p2"] * (r2 + 2 * x * x),
                y * radial + c["p1"] * (r2 + 2 * y * y) + 2 * c["p2"] * x * y)
    r = np.hypot(x, y)
    t = np.arctan(r)
    td = t * (1 + c["k1"] * t**2 + c["k2"] * t**4 + c["k3"] * t**6 + c["k4"] * t**8)
    return x * td / r, y * td / r


def inverse(model: str, c: dict, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted coordinates of distorted ones, by a method of the test's own."""
    if model == "OPENCV":
        # OpenCV's undistortPoints iteration: x = (x_d - tangential(x)) / radial(x).
        x, y = xd.copy(), yd.copy()
        for _ in range(500):
            r2 = x * x + y * y
            radial = 1 + c["k1"] * r2 + c["k2"] * r2**2
            x = (xd - 2 * c["p1"] * x * y - c["p2"] * (r2 + 2 * x * x)) / radial
            y = (yd - c["p1"] * (r2 + 2 * y * y) - 2 * c["p2"] * x * y) / radial
    else:
        # theta_d(theta) = |xy_d| by bisection on [0, 90 degrees).
        rho = np.hypot(xd, yd)
        lo, hi = np.zeros_like(rho), np.full_like(rho, math.pi / 2 - 1e-9)
        for _ in range(80):
            t = 0.5 * (lo + hi)
            td = t * (1 + c["k1"] * t**2 + c["k2"] * t**4 + c["k3"] * t**6 + c["k4"] * t**8)
            lo, hi = np.where(td < rho, t, lo), np.where(td < rho, hi, t)
        r = np.tan(0.5 * (lo + hi))
        x, y = xd * r / rho, yd * r / rho
    fx, fy = forward(model, c, x, y)
    assert max(np.abs(fx - xd).max(), np.abs(fy - yd).max()) < 1e-12  # the inverse is one
    return x, y


def distorted_depth(model: str, c: dict, pose: np.ndarray) -> np.ndarray:
    """(H, W) z-depth in metres of the room through each pixel centre's TRUE (distorted) ray."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    x, y = inverse(model, c, (u - CX) / FX, (v - CY) / FY)
    d = np.stack([x, y, np.ones_like(x)], -1) @ pose[:3, :3].T  # z = 1 in the camera
    o = pose[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (ROOM[1] - o) / d, (ROOM[0] - o) / d)
    t[~np.isfinite(t)] = np.inf
    return t.min(axis=-1)


def write_distorted(root: Path, model: str) -> None:
    """The room capture seen through ``model``'s lens, coefficients at the top level."""
    write_nerfstudio(root, extra={"camera_model": model, **LENSES[model]})
    for i, pose in enumerate(truth_poses()):
        mm = np.round(distorted_depth(model, LENSES[model], pose) * 1000.0)
        assert mm.max() < 65535
        iio.imwrite(root / "depth" / f"frame_{i:05d}.png", mm.astype(np.uint16))


def room_distance(points_m: np.ndarray) -> np.ndarray:
    """(n,) unsigned distance in metres from each point to the room's walls, floor and ceiling."""
    inside = np.minimum(points_m - ROOM[0], ROOM[1] - points_m).min(-1)
    outside = np.linalg.norm(np.maximum(np.maximum(ROOM[0] - points_m, points_m - ROOM[1]), 0.0), axis=-1)
    return np.where(inside > 0, inside, outside)


def surface_errors(capture: Capture) -> np.ndarray:
    """Distance to the room of every training point :func:`build_samples` back-projects, metres."""
    samples = build_samples(capture, range(len(capture.frames)))
    p = samples.points.double().numpy()
    M = capture.worldtogt
    return room_distance(p @ M[:3, :3].T + M[:3, 3])


@pytest.mark.parametrize("model", LENSES)
def test_distorted_depth_back_projects_onto_the_room(tmp_path: Path, model: str) -> None:
    write_distorted(tmp_path / "lens", model)
    capture, _ = read_capture(tmp_path / "lens")
    assert all(f.distortion is not None and f.distortion.model == model for f in capture.frames)
    err = surface_errors(capture)
    assert len(err) > 0.5 * len(capture.frames) * W * H
    # Millimetre depth: 0.5 mm of z-depth moves a point by at most 0.5 mm times its ray's length
    # (z = 1): about 1 mm at the corners.
    v, u = np.mgrid[0:H, 0:W] + 0.5
    x, y = inverse(model, LENSES[model], (u - CX) / FX, (v - CY) / FY)
    widest = float(np.sqrt(1.0 + x**2 + y**2).max())
    assert err.max() < 0.5e-3 * widest + 1e-6, (err.max(), widest)

    # The same files with the distortion dropped: the pinhole rays miss the walls near the corners.
    shutil.copytree(tmp_path / "lens", tmp_path / "pinhole")
    data = json.loads((tmp_path / "pinhole" / "transforms.json").read_text())
    data.update(camera_model="PINHOLE", **dict.fromkeys(LENSES[model], 0.0))
    (tmp_path / "pinhole" / "transforms.json").write_text(json.dumps(data))
    pinhole, _ = read_capture(tmp_path / "pinhole")
    assert all(f.distortion is None for f in pinhole.frames)
    assert surface_errors(pinhole).max() > 0.05


def test_per_frame_coefficients_and_zero_ones(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path, extra={"camera_model": "OPENCV"})
    data = json.loads((tmp_path / "transforms.json").read_text())
    data["frames"][2].update(k1=0.1, p2=1e-3)
    data["frames"][5].update(k1=0.0, k2=0.0)  # written out, all zero: a pinhole
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    capture, _ = read_capture(tmp_path)
    lenses = [f.distortion for f in capture.frames]
    assert lenses[2] is not None and lenses[2].coefficients() == (0.1, 0.0, 0.0, 0.0, 0.0, 1e-3)
    assert [i for i, d in enumerate(lenses) if d is not None] == [2]
