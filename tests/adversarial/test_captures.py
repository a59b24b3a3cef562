"""Hostile captures: paths leading out of the folder, poses that are not rigid, bad
intrinsics, depth that is not a real z-depth. Each is a one-line CaptureError naming the file
and the frame, from the loader, from training and from the renderer's cameras alike."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh

from regnf.captures import sdfstudio
from regnf.captures.instance import Instance, box_corners, yaw_pose
from regnf.captures.model import CaptureError, normalisation
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.compositor.cameras_io import cameras_from_capture
from regnf.core.cameras import look_at
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.render.camera import Camera
from regnf.training.training import RGBDTrainConfig, train_rgbd

W, H, N = 16, 12, 3
K = np.array([[14.0, 0.0, 8.0], [0.0, 15.0, 6.0], [0.0, 0.0, 1.0]])
TINY = NeuralSDFConfig(levels=2, finest_resolution=16, hidden_dim=16, base_resolution=8,
                       geo_feature_dim=3, color_hidden_dim=8)
"""As tests/scene_graph/helpers.py."""


def make_capture(root: Path) -> Path:
    """A 3-frame 16 x 12 capture with an instance mesh and a ground-truth mesh, in ``root/cap``."""
    cap = root / "cap"
    rng = np.random.default_rng(0)
    rgbs = [rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8) for _ in range(N)]
    depths = [rng.uniform(0.5, 4.0, size=(H, W)).astype(np.float32) for _ in range(N)]
    poses = np.stack([look_at(rng.normal(size=3) * 2 + [0, 0, 2], [0.1, 0.2, 0.3]) for _ in range(N)])
    box = trimesh.creation.box((0.4, 0.3, 0.5))
    mesh_path = cap / "meshes" / "c_0.ply"
    mesh_path.parent.mkdir(parents=True)
    box.export(mesh_path)
    box.export(cap / "gt_mesh.ply")
    pose = yaw_pose(0.7, np.array([0.5, -0.2, 0.0]))
    inst = Instance("c_0", "c", "chair", pose, 1.0, 0.7, box_corners(box.bounds, pose), mesh_path=mesh_path)
    # Zeros mean empty: there NaN and inf depth are refused (elsewhere they mean unknown).
    meta = {"kind": "scene", "name": "unit", "gt_mesh_path": "gt_mesh.ply", "zero_depth": "empty"}
    worldtogt = normalisation(np.array([[-1.0, -0.5, 0.0], [2.0, 1.0, 1.5]]), 1.02)
    write_capture(cap, rgbs, depths, poses, K, worldtogt, [inst], meta)
    # A file beside the capture, which nothing in it may name.
    iio.imwrite(root / "outside.png", rgbs[0])
    np.save(root / "outside.npy", depths[0])
    return cap


@pytest.fixture
def cap(tmp_path: Path) -> Path:
    return make_capture(tmp_path)


def edit_meta(cap: Path, fn: Callable[[dict], None]) -> Path:
    meta = cap / "meta_data.json"
    data = json.loads(meta.read_text())
    fn(data)
    meta.write_text(json.dumps(data))
    return meta


def _scale_rotation(d: dict, frame: int, factor: float) -> None:
    pose = np.array(d["frames"][frame]["camtoworld"])
    pose[:3, :3] *= factor
    d["frames"][frame]["camtoworld"] = pose.tolist()


def refused(fn: Callable[[], object], file: Path, frame: str, match: str) -> str:
    """The one-line CaptureError of ``fn()``, which names ``file`` and ``frame``."""
    with pytest.raises(CaptureError, match=match) as info:
        fn()
    message = str(info.value)
    assert str(file) in message and frame in message and "\n" not in message, message
    return message


# -- paths ---------------------------------------------------------------------------------------
PATH_KEYS = [
    (lambda d, v: d["frames"][1].__setitem__("rgb_path", v), "frames[1].rgb_path"),
    (lambda d, v: d["frames"][2].__setitem__("sensor_depth_path", v), "frames[2].sensor_depth_path"),
    (lambda d, v: d["frames"][0].__setitem__("mono_depth_path", v), "frames[0].mono_depth_path"),
    (lambda d, v: d["instances"][0].__setitem__("mesh_path", v), "instances[0].mesh_path"),
    (lambda d, v: d["regnf"].__setitem__("gt_mesh_path", v), "regnf.gt_mesh_path"),
]


@pytest.mark.parametrize(("put", "where"), PATH_KEYS, ids=[w for _, w in PATH_KEYS])
@pytest.mark.parametrize("form", ["dotdot", "absolute", "nested-dotdot"])
def test_a_path_outside_the_capture_is_refused(cap: Path, put, where: str, form: str) -> None:
    target = {"dotdot": "../outside.png", "absolute": str(cap.parent / "outside.png"),
              "nested-dotdot": "meshes/../../outside.png"}[form]
    meta = edit_meta(cap, lambda d: put(d, target))
    refused(lambda: load_capture(cap), meta, where, "outside the capture folder")


def test_a_symlink_leading_outside_is_refused(cap: Path, tmp_path: Path) -> None:
    # Symlinks that stay inside are fine: the folder itself through a link, a file linked
    # to another file of the capture.
    os.symlink(cap, tmp_path / "link")
    (cap / "000001_rgb.png").rename(cap / "real_rgb.png")
    os.symlink("real_rgb.png", cap / "000001_rgb.png")
    loaded = load_capture(tmp_path / "link")
    assert loaded.root == tmp_path / "link" and loaded.rgb(1).shape == (H, W, 3)
    # One leading out of the folder is not, absolute or relative, whichever way it is reached.
    (cap / "000001_rgb.png").unlink()
    os.symlink(cap.parent / "outside.png", cap / "000001_rgb.png")
    for spelling in (cap, tmp_path / "link"):
        refused(lambda spelling=spelling: load_capture(spelling), spelling / "meta_data.json",
                "frames[1].rgb_path", "outside the capture folder")
    (cap / "000001_rgb.png").unlink()
    (cap / "real_rgb.png").rename(cap / "000001_rgb.png")
    (cap / "000002_depth.npy").unlink()
    os.symlink("../outside.npy", cap / "000002_depth.npy")
    refused(lambda: load_capture(cap), cap / "meta_data.json", "frames[2].sensor_depth_path", "outside")


def test_poses_are_checked_before_any_image_is_read(cap: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args, **kwargs):
        raise AssertionError("load_capture read an image")

    monkeypatch.setattr(sdfstudio.iio, "imread", forbidden)
    monkeypatch.setattr(sdfstudio.np, "load", forbidden)
    assert len(load_capture(cap).frames) == N
    meta = edit_meta(cap, lambda d: _scale_rotation(d, 0, 2.0))
    refused(lambda: load_capture(cap), meta, "frames[0].camtoworld", "rigid")


# -- poses: one rule for training and rendering ----------------------------------------------
def test_a_rotation_scaled_by_7_is_refused_by_training_and_rendering_alike(cap: Path) -> None:
    def round_poses(d: dict) -> None:  # float32 rounding is no scale: these still load
        for f in d["frames"]:
            f["camtoworld"] = np.asarray(f["camtoworld"], np.float32).astype(np.float64).tolist()

    edit_meta(cap, round_poses)
    assert len(cameras_from_capture(cap)) == len(load_capture(cap).frames) == N
    meta = edit_meta(cap, lambda d: _scale_rotation(d, 2, 7.0))
    trained = refused(lambda: load_capture(cap), meta, "frames[2].camtoworld", r"must be rigid \(scale 1\), got scale 7")
    rendered = refused(lambda: cameras_from_capture(cap), meta, "frames[2]", "rigid")
    assert rendered == trained
    # A camera built by hand with that pose is refused by the very same rule.
    pose = look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    pose[:3, :3] *= 7.0
    with pytest.raises(ValueError) as info:
        Camera(K, W, H, pose)
    assert str(info.value) == "camera_to_world: " + trained.split("camtoworld: ", 1)[1]


@pytest.mark.parametrize(
    ("linear", "match"),
    [
        (np.zeros((3, 3)), "determinant 0"),
        (np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), "determinant 0"),
        (np.diag([1.0, 1.0, -1.0]), "reflection"),
        (np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "shear"),
    ],
    ids=["zero", "rank-2", "mirror", "shear"],
)
def test_a_singular_or_improper_pose_is_refused(cap: Path, linear: np.ndarray, match: str) -> None:
    def edit(d: dict) -> None:
        pose = np.array(d["frames"][1]["camtoworld"])
        pose[:3, :3] = linear
        d["frames"][1]["camtoworld"] = pose.tolist()

    meta = edit_meta(cap, edit)
    refused(lambda: load_capture(cap), meta, "frames[1].camtoworld", match)
    refused(lambda: cameras_from_capture(cap), meta, "frames[1].camtoworld", match)


def test_a_worldtogt_that_is_no_similarity_is_refused(cap: Path) -> None:
    def stretch(d: dict) -> None:
        d["worldtogt"][1][1] *= 2.0

    meta = edit_meta(cap, stretch)
    with pytest.raises(CaptureError, match="worldtogt: not a uniformly scaled rotation") as info:
        load_capture(cap)
    assert str(meta) in str(info.value)


# -- intrinsics -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("row", "col", "value", "match"),
    [
        (0, 0, 0.0, "focal lengths must be > 0, got fx = 0"),
        (1, 1, -15.0, "focal lengths must be > 0, got fx = 14, fy = -15"),
        (2, 2, 0.0, "not a pinhole K"),
    ],
    ids=["fx-zero", "fy-negative", "no-homogeneous-row"],
)
def test_bad_intrinsics_are_refused(cap: Path, row: int, col: int, value: float, match: str) -> None:
    meta = edit_meta(cap, lambda d: d["frames"][2]["intrinsics"][row].__setitem__(col, value))
    refused(lambda: load_capture(cap), meta, "frames[2].intrinsics", match)
    refused(lambda: cameras_from_capture(cap), meta, "frames[2].intrinsics", match)


def test_all_zero_intrinsics_are_refused_by_the_camera_too(cap: Path) -> None:
    meta = edit_meta(cap, lambda d: d["frames"][0].__setitem__("intrinsics", np.zeros((4, 4)).tolist()))
    message = refused(lambda: load_capture(cap), meta, "frames[0].intrinsics", "focal lengths must be > 0")
    with pytest.raises(ValueError) as info:
        Camera(np.zeros((3, 3)), W, H, np.eye(4))
    assert str(info.value) == "K: " + message.split("intrinsics: ", 1)[1]


# -- depth ----------------------------------------------------------------------------------------
BAD_DEPTHS = {
    "complex": (lambda d: d.astype(np.complex64), "dtype complex64"),
    "int": (lambda d: (d * 1000).astype(np.int32), "dtype int32"),
    "uint16": (lambda d: (d * 1000).astype(np.uint16), "dtype uint16"),
    "bool": (lambda d: d > np.median(d), "dtype bool"),
    "negative": (lambda d: np.where(d > np.median(d), -d, d), "negative values"),
    "nan": (lambda d: np.where(d > np.median(d), np.nan, d), "non-finite"),
    "inf": (lambda d: np.where(d > np.median(d), np.inf, d), "non-finite"),
    "float64-overflow": (lambda d: np.where(d > np.median(d), 1e300, d.astype(np.float64)), "non-finite"),
    "shape": (lambda d: d[:, :5], "shape"),
}


@pytest.mark.parametrize("kind", list(BAD_DEPTHS))
def test_bad_depth_is_refused_when_read_and_before_training(cap: Path, kind: str) -> None:
    make, match = BAD_DEPTHS[kind]
    name = cap / "000001_depth.npy"
    np.save(name, make(np.load(name)), allow_pickle=False)
    capture = load_capture(cap)
    assert capture.depth(0) is not None  # the other frames are fine
    refused(lambda: capture.depth(1), name, "frame 1", match)
    config = RGBDTrainConfig(steps=1, batch_surface=64, batch_free=32, batch_empty=32, batch_eikonal=16,
                             architecture=TINY)
    refused(lambda: train_rgbd(capture, config, progress=False), name, "frame 1", match)


def test_a_pickled_or_unreadable_depth_is_refused(cap: Path) -> None:
    name = cap / "000002_depth.npy"
    np.save(name, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    refused(lambda: load_capture(cap).depth(2), name, "frame 2", "cannot read depth")
    name.write_bytes(name.read_bytes()[:40])
    refused(lambda: load_capture(cap).depth(2), name, "frame 2", "cannot read depth")


def test_a_forged_huge_depth_header_costs_nothing(cap: Path) -> None:
    # An .npy header claiming a terabyte array over a few bytes of data: refused from the header.
    name = cap / "000000_depth.npy"
    with open(name, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f4", "fortran_order": False, "shape": (500_000, 500_000)}
        )
    refused(lambda: load_capture(cap).depth(0), name, "frame 0", "cannot read depth|shape")


def test_a_bad_image_names_its_frame(cap: Path) -> None:
    name = cap / "000002_rgb.png"
    iio.imwrite(name, np.zeros((H, W, 2), np.uint8))  # grey + alpha: not RGB
    refused(lambda: load_capture(cap).rgb(2), name, "frame 2", "image shape")
    name.write_bytes(b"not a png")
    refused(lambda: load_capture(cap).rgb(2), name, "frame 2", "cannot read image")
