"""meta_data.json writer / loader: exact round trip, clear errors, plain sdfstudio folders."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh

from regnf.captures.instance import Instance, box_corners, yaw_pose
from regnf.captures.model import CaptureError, normalisation
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.core.cameras import look_at
from regnf.synthetic.library import instance_mesh

W, H, N = 16, 12, 3
K = np.array([[14.0, 0.0, 8.0], [0.0, 15.0, 6.0], [0.0, 0.0, 1.0]])


def _write(out: Path) -> dict:
    rng = np.random.default_rng(0)
    rgbs = [rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8) for _ in range(N)]
    depths = [rng.uniform(0.5, 4.0, size=(H, W)).astype(np.float32) for _ in range(N)]
    depths[0][:3] = 0.0  # no hit
    poses = np.stack(
        [look_at(rng.normal(size=3) * 2 + [0, 0, 2], [0.1, 0.2, 0.3]) for _ in range(N)]
    )
    bounds = np.array([[-1.0, -0.5, 0.0], [2.0, 1.0, 1.5]])
    worldtogt = normalisation(bounds, 1.02)
    box = trimesh.creation.box((0.4, 0.3, 0.5))
    box.visual.face_colors = [10, 20, 30, 255]
    mesh_path = out / "meshes" / "c_0.ply"
    mesh_path.parent.mkdir(parents=True)
    box.export(mesh_path)
    pose = yaw_pose(0.7, np.array([0.5, -0.2, 0.0]))
    inst = Instance(
        "c_0", "c", "chair", pose, 1.0, 0.7, box_corners(box.bounds, pose), mesh_path=mesh_path
    )
    meta = {"kind": "scene", "name": "unit", "gt_mesh_path": "gt_mesh.ply", "seed": 3}
    splits = ["train", "test", "train"]
    write_capture(out, rgbs, depths, poses, K, worldtogt, [inst], meta, splits)
    return {
        "rgbs": rgbs,
        "depths": depths,
        "poses": poses,
        "worldtogt": worldtogt,
        "inst": inst,
        "meta": meta,
    }


def test_round_trip_is_exact(tmp_path: Path) -> None:
    ref = _write(tmp_path)
    cap = load_capture(tmp_path)
    assert load_capture(tmp_path / "meta_data.json").frames[2].rgb_path == cap.frames[2].rgb_path
    assert (cap.width, cap.height, len(cap.frames)) == (W, H, N)
    np.testing.assert_array_equal(cap.worldtogt, ref["worldtogt"])
    s, c = ref["worldtogt"][0, 0], ref["worldtogt"][:3, 3]
    assert cap.scale == pytest.approx(s, rel=1e-12)
    assert cap.train_indices() == [0, 2] and cap.test_indices() == [1]
    for i in range(N):
        f = cap.frames[i]
        np.testing.assert_array_equal(f.intrinsics, K)
        expected = ref["poses"][i].copy()
        expected[:3, 3] = (expected[:3, 3] - c) / s
        np.testing.assert_array_equal(f.camtoworld, expected)
        np.testing.assert_allclose(cap.camtoworld_metres(i), ref["poses"][i], atol=1e-12)
        rgb = cap.rgb(i)
        assert rgb.dtype == np.float32 and rgb.shape == (H, W, 3)
        np.testing.assert_array_equal(np.round(rgb * 255).astype(np.uint8), ref["rgbs"][i])
        depth = cap.depth(i)
        assert depth.dtype == np.float32
        np.testing.assert_array_equal(depth, ref["depths"][i] / np.float32(s))
    assert np.all(cap.depth(0)[:3] == 0)
    (inst,) = cap.instances
    want = ref["inst"]
    assert (inst.id, inst.library, inst.label, inst.scale, inst.yaw) == (
        "c_0",
        "c",
        "chair",
        1.0,
        0.7,
    )
    np.testing.assert_array_equal(inst.object_to_world, want.object_to_world)
    np.testing.assert_array_equal(inst.box_corners, want.box_corners)
    assert inst.mesh_path == tmp_path / "meshes" / "c_0.ply"
    assert np.all(instance_mesh(inst).visual.face_colors[:, :3] == [10, 20, 30])
    assert cap.meta == ref["meta"]
    data = json.loads((tmp_path / "meta_data.json").read_text())
    assert data["camera_model"] == "OPENCV" and data["has_sensor_depth"] is True
    assert data["instances"][0]["mesh_path"] == "meshes/c_0.ply"
    assert data["scene_box"]["aabb"] == [[-1, -1, -1], [1, 1, 1]]
    assert data["scene_box"]["far"] > data["scene_box"]["near"] > 0
    assert cap.gt_mesh() is None  # named but not written here


def test_meta_is_written_last(tmp_path: Path) -> None:
    rgbs = [np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.uint8)]  # second frame is bad
    poses = np.stack([np.eye(4)] * 2)
    with pytest.raises(ValueError, match="frame 1"):
        write_capture(tmp_path, rgbs, None, poses, K, np.eye(4))
    assert (tmp_path / "000000_rgb.png").exists()
    assert not (tmp_path / "meta_data.json").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def _edit(tmp_path: Path, fn) -> None:
    meta = tmp_path / "meta_data.json"
    data = json.loads(meta.read_text())
    fn(data)
    meta.write_text(json.dumps(data))


def test_missing_folder_or_meta(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="meta_data.json.*not found"):
        load_capture(tmp_path / "nowhere")
    with pytest.raises(CaptureError, match="meta_data.json"):
        load_capture(tmp_path)


@pytest.mark.parametrize("text", ['{"height": 12, "width": 16, "fra', "garbage{{", "[1, 2]", ""])
def test_bad_json(tmp_path: Path, text: str) -> None:
    _write(tmp_path)
    (tmp_path / "meta_data.json").write_text(text)
    with pytest.raises(CaptureError, match="meta_data.json"):
        load_capture(tmp_path)


@pytest.mark.parametrize(
    "edit, pattern",
    [
        (lambda d: d.pop("frames"), "missing key 'frames'"),
        (lambda d: d["frames"][1].pop("camtoworld"), r"frames\[1\] is missing key 'camtoworld'"),
        (
            lambda d: d["frames"].__setitem__(
                1, {**d["frames"][1], "camtoworld": np.eye(3).tolist()}
            ),
            r"frames\[1\]\.camtoworld must be 4x4 or 3x4, got shape \(3, 3\)",
        ),
        (
            lambda d: d["frames"][0]["intrinsics"].__setitem__(0, [1.0, 2.0]),
            r"frames\[0\]\.intrinsics",
        ),
        (lambda d: d["worldtogt"][0].__setitem__(0, float("nan")), "worldtogt has non-finite"),
        (lambda d: d["frames"][2]["camtoworld"][1].__setitem__(3, float("inf")), "non-finite"),
        (lambda d: d["frames"][2].__setitem__("split", "holdout"), r"frames\[2\]\.split"),
        (
            lambda d: d["instances"][0].__setitem__("box_corners", [[0, 0, 0]]),
            r"box_corners must be 8x3",
        ),
        (lambda d: d.__setitem__("camera_model", "OPENCV_FISHEYE"), "camera_model"),
        (lambda d: d["scene_box"].__setitem__("aabb", [1, 2]), r"scene_box\.aabb must be 2x3"),
    ],
)
def test_malformed_entries_name_the_file_and_entry(tmp_path: Path, edit, pattern: str) -> None:
    _write(tmp_path)
    _edit(tmp_path, edit)
    with pytest.raises(CaptureError, match=pattern) as info:
        load_capture(tmp_path)
    assert str(tmp_path / "meta_data.json") in str(info.value)


@pytest.mark.parametrize("name", ["000001_rgb.png", "000002_depth.npy", "meshes/c_0.ply"])
def test_missing_data_files(tmp_path: Path, name: str) -> None:
    _write(tmp_path)
    (tmp_path / name).unlink()
    with pytest.raises(CaptureError, match=name):
        load_capture(tmp_path)


def test_corrupt_depth_and_image_name_the_file(tmp_path: Path) -> None:
    _write(tmp_path)
    np.save(tmp_path / "000001_depth.npy", np.zeros((3, 3), np.float32))
    (tmp_path / "000002_rgb.png").write_bytes(b"not a png")
    cap = load_capture(tmp_path)
    with pytest.raises(CaptureError, match="000001_depth.npy.*shape"):
        cap.depth(1)
    with pytest.raises(CaptureError, match="000002_rgb.png"):
        cap.rgb(2)


def test_loads_a_plain_sdfstudio_folder(tmp_path: Path) -> None:
    """As sdfstudio writes it: 3x3 intrinsics, mono depth only, no worldtogt/instances/splits."""
    frames = []
    for i in range(2):
        iio.imwrite(tmp_path / f"{i:06d}_rgb.png", np.full((6, 8, 3), 40 * i, np.uint8))
        np.save(tmp_path / f"{i:06d}_depth.npy", np.ones((6, 8), np.float32))
        pose = np.eye(4)
        pose[0, 3] = i
        frames.append(
            {
                "rgb_path": f"{i:06d}_rgb.png",
                "camtoworld": pose.tolist(),
                "intrinsics": [[5.0, 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]],
                "mono_depth_path": f"{i:06d}_depth.npy",
            }
        )
    meta = {
        "camera_model": "OPENCV",
        "height": 6,
        "width": 8,
        "has_mono_prior": True,
        "pairs": None,
        "scene_box": {
            "aabb": [[-1, -1, -1], [1, 1, 1]],
            "near": 0.5,
            "far": 4.5,
            "radius": 1.0,
            "collider_type": "near_far",
        },
        "frames": frames,
    }
    (tmp_path / "meta_data.json").write_text(json.dumps(meta))
    cap = load_capture(tmp_path)
    np.testing.assert_array_equal(cap.worldtogt, np.eye(4))
    assert cap.instances == [] and cap.meta == {}
    assert cap.depth(0) is None and cap.frames[1].mono_depth_path == tmp_path / "000001_depth.npy"
    assert cap.train_indices() == [0, 1] and cap.test_indices() == []
    assert cap.scene_box["near"] == 0.5 and cap.scene_box["collider_type"] == "near_far"
    assert cap.scene_box["aabb"].shape == (2, 3)
    np.testing.assert_array_equal(cap.frames[0].intrinsics[0], [5.0, 0.0, 4.0])
    assert cap.rgb(1)[0, 0, 0] == pytest.approx(40 / 255)
    assert cap.gt_mesh() is None
