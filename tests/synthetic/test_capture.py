"""End-to-end captures: stored depth + poses land on the ground-truth mesh; determinism."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from regnf.captures.model import Capture
from regnf.synthetic.capture import (
    ObjectCaptureConfig,
    RoomCaptureConfig,
    capture_object,
    capture_room,
)
from regnf.synthetic.library import make_library_object

from .synth_helpers import backproject, erode

OBJ = ObjectCaptureConfig(width=64, height=64, n_views=12, progress=False)
ROOM = RoomCaptureConfig(width=64, height=48, n_views=10, coverage="low", seed=2, progress=False)


def _surface_distance(cap: Capture, frames: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Distances (metres) from back-projected depth pixels (eroded hit masks) to the GT mesh,
    and the same points in the normalised frame."""
    gt = cap.gt_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(gt.vertices.astype(np.float32)), o3d.core.Tensor(gt.faces.astype(np.uint32))
    )
    dists, normalised = [], []
    for i in frames:
        depth = cap.depth(i)
        f = cap.frames[i]
        keep = erode(depth > 0)
        pts_n = backproject(depth.astype(np.float64), f.camtoworld, f.intrinsics)[keep]
        pts_m = pts_n @ cap.worldtogt[:3, :3].T + cap.worldtogt[:3, 3]
        dists.append(scene.compute_distance(o3d.core.Tensor(pts_m.astype(np.float32))).numpy())
        normalised.append(pts_n)
    return np.concatenate(dists), np.concatenate(normalised)


def test_object_capture(tmp_path: Path) -> None:
    cap = capture_object("et", tmp_path, OBJ)
    assert (cap.width, cap.height, len(cap.frames)) == (64, 64, 12)
    assert cap.test_indices() == [9] and len(cap.train_indices()) == 11
    assert cap.instances == []
    assert cap.meta["kind"] == "object" and cap.meta["label"] == "table"
    assert cap.meta["symmetry"] == {"axis": "z", "order": 4}
    mesh = make_library_object("et").mesh
    gt = cap.gt_mesh()
    np.testing.assert_allclose(gt.vertices, mesh.vertices, atol=1e-6)
    # Trained at its own scale: 1.15 x half the largest extent, centred on the bbox.
    assert cap.scale == pytest.approx(1.15 * 0.5 * mesh.extents.max())
    np.testing.assert_allclose(cap.worldtogt[:3, 3], mesh.bounds.mean(axis=0), atol=1e-12)
    dist, pts_n = _surface_distance(cap, list(range(12)))
    assert np.median(dist) < 5e-4 and np.percentile(dist, 99) < 3e-3
    assert np.all(np.abs(pts_n) < 1.0)  # the object fits in the scene box
    for i in (0, 5):
        hit = cap.depth(i) > 0
        assert 0.1 < hit.mean() < 0.8  # the object fills a good part of the image
        grey = cap.rgb(i)[erode(~hit, 2)]
        np.testing.assert_allclose(grey, 128 / 255, atol=1 / 255)


def test_room_capture(tmp_path: Path) -> None:
    cap = capture_room("mix-room", tmp_path, ROOM)
    assert len(cap.frames) == 10 and cap.test_indices() == [9]
    assert cap.meta["kind"] == "scene" and cap.meta["coverage"] == "low" and cap.meta["seed"] == 2
    assert [i.id for i in cap.instances] == ["dc_0", "fc_0", "t_0"]
    for inst in cap.instances:
        assert inst.mesh_path == tmp_path / "meshes" / f"{inst.id}.ply"
    gt = cap.gt_mesh()
    assert cap.scale == pytest.approx(1.02 * 0.5 * gt.extents.max())
    dist, pts_n = _surface_distance(cap, [0, 4, 9])
    assert np.median(dist) < 1e-3 and np.percentile(dist, 99) < 5e-3
    assert np.all(np.abs(pts_n) < 1.0)
    with pytest.raises(ValueError, match="coverage"):
        capture_room("mix-room", tmp_path / "x", RoomCaptureConfig(coverage="some"))


def _folder_contents(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.mark.parametrize("kind", ["object", "room"])
def test_same_seed_same_capture(tmp_path: Path, kind: str) -> None:
    if kind == "object":
        a = capture_object("fc", tmp_path / "a", OBJ)
        b = capture_object("fc", tmp_path / "b", OBJ)
    else:
        a = capture_room("ac-room", tmp_path / "a", ROOM)
        b = capture_room("ac-room", tmp_path / "b", ROOM)
    fa, fb = _folder_contents(a.root), _folder_contents(b.root)
    assert fa.keys() == fb.keys()
    assert "meta_data.json" in fa and "gt_mesh.ply" in fa
    assert fa["meta_data.json"] == fb["meta_data.json"]
    for key in fa:  # images, depths and meshes byte for byte
        assert fa[key] == fb[key], key
    for i in range(len(a.frames)):
        np.testing.assert_array_equal(a.rgb(i), b.rgb(i))
        np.testing.assert_array_equal(a.depth(i), b.depth(i))
    if kind == "room":
        c = capture_room(
            "ac-room", tmp_path / "c", RoomCaptureConfig(**{**ROOM.__dict__, "seed": 3})
        )
        assert _folder_contents(c.root)["meta_data.json"] != fa["meta_data.json"]
