"""pyrender RGB-D against independent Open3D ray casts of the same meshes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from regnf.core.cameras import look_at
from regnf.core.image_io import rgb_to_uint8
from regnf.synthetic.library import make_library_object
from regnf.synthetic.render import VOID_GREY, RGBDRenderer
from regnf.synthetic.rooms import make_room
from regnf.synthetic.shading import shaded_copy
from regnf.synthetic.trajectories import object_capture_poses

from .synth_helpers import erode, raycast

W, H = 96, 80
K = np.array([[110.0, 0.0, 47.0], [0.0, 112.0, 41.5], [0.0, 0.0, 1.0]])  # off-centre on purpose


def _compare_depth(depth: np.ndarray, t_hit: np.ndarray) -> None:
    hit_ref = np.isfinite(t_hit)
    hit = depth > 0
    # Hit masks agree except on a 1-pixel band around silhouettes.
    boundary = hit_ref & ~erode(hit_ref) | ~hit_ref & ~erode(~hit_ref)
    assert np.all((hit == hit_ref) | boundary)
    assert np.mean(hit != hit_ref) < 0.01
    inner = erode(hit_ref) & hit
    err = np.abs(depth[inner] - t_hit[inner])
    assert inner.sum() > 200
    assert np.median(err) < 1e-3
    assert np.percentile(err, 99) < 5e-3


@pytest.mark.parametrize("name", ["dc", "fc", "wt"])
def test_object_depth_matches_raycast(name: str) -> None:
    mesh = make_library_object(name).mesh
    c = mesh.bounds.mean(axis=0)
    poses = object_capture_poses(c, 0.5 * np.linalg.norm(mesh.extents), 4, K, W, H)
    with RGBDRenderer([shaded_copy(mesh)], W, H) as renderer:
        for pose in poses:
            out = renderer.render(pose, K)
            assert out.rgb.shape == (H, W, 3) and out.rgb.dtype == torch.float32
            assert out.depth.shape == (H, W) and out.depth.dtype == torch.float32
            assert out.normals is None and out.evals_per_pixel is None
            t_hit, _gid = raycast([mesh], pose, K, W, H)
            depth = out.depth.numpy()
            _compare_depth(depth, t_hit)
            assert np.all(depth[~np.isfinite(t_hit) & erode(~np.isfinite(t_hit))] == 0)
            assert np.array_equal(out.mask.numpy(), depth > 0)
            # Unlabelled geometry and background are both -1.
            assert bool((out.instance_id == -1).all())


def test_flat_colours_are_the_baked_face_colours_and_background_is_grey() -> None:
    mesh = shaded_copy(make_library_object("t").mesh)
    pose = look_at([1.8, 1.2, 1.6], mesh.bounds.mean(axis=0))
    with RGBDRenderer([mesh], W, H) as renderer:
        out = renderer.render(pose, K)
    rgb = rgb_to_uint8(out.rgb)
    # The float colours are exactly the 8-bit ones over 255.
    assert torch.equal(out.rgb, torch.from_numpy(rgb).float() / 255.0)
    t_hit, _ = raycast([mesh], pose, K, W, H)
    o3d_scene_faces = _face_ids(mesh, pose)
    hit = np.isfinite(t_hit)
    colors = np.asarray(mesh.visual.face_colors)[:, :3].astype(int)
    expected = np.where(hit[..., None], colors[np.where(hit, o3d_scene_faces, 0)], -1)
    # Pixels whose 4-neighbours have the same expected colour: away from colour edges, where
    # pyrender's MSAA blends neighbouring colours.
    code = expected[..., 0] * 65536 + expected[..., 1] * 256 + expected[..., 2]
    inner = erode(hit, 1)
    for k in np.unique(code[hit]):
        inner &= erode(code == k) | (code != k)
    assert inner.sum() > 200
    diff = np.abs(rgb[inner].astype(int) - expected[inner]).max(axis=1)
    assert np.mean(diff <= 1) > 0.99
    background = erode(~np.isfinite(t_hit), 2)
    assert np.all(np.abs(rgb[background].astype(int) - 255 * np.array(VOID_GREY)) <= 1)


def _face_ids(mesh, pose) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(
        -1, 3
    )
    d = d @ pose[:3, :3].T
    rays = np.concatenate([np.broadcast_to(pose[:3, 3], d.shape), d], 1).astype(np.float32)
    prim = scene.cast_rays(o3d.core.Tensor(rays))["primitive_ids"].numpy().astype(np.int64)
    return prim.reshape(H, W)


def test_room_depth_and_instance_ids_match_raycast() -> None:
    room = make_room("ac-room", seed=1)
    meshes = room.instance_meshes()
    world = [room.mesh, *meshes]
    with RGBDRenderer(
        [shaded_copy(m) for m in world], W, H, instance_ids=[-1, *range(len(meshes))]
    ) as renderer:
        for eye in ([2.5, -2.0, 2.0], [-2.6, 2.1, 1.4]):
            pose = look_at(eye, [0.0, 0.0, 0.3])
            out = renderer.render(pose, K)
            ids = out.instance_id.numpy()
            t_hit, gid = raycast(world, pose, K, W, H)
            _compare_depth(out.depth.numpy(), t_hit)
            expected = gid - 1  # geometry 0 is the room shell: -1
            expected[gid < 0] = -1
            # Ids agree away from the boundaries between differently labelled regions.
            same = np.ones_like(expected, dtype=bool)
            for k in np.unique(expected):
                same &= erode(expected == k) | (expected != k)
            assert np.all(ids[same] == expected[same])
            assert len(np.unique(ids)) >= 3


def test_renderer_validates_inputs() -> None:
    mesh = make_library_object("c").mesh
    with pytest.raises(ValueError, match="one instance id per mesh"):
        RGBDRenderer([mesh], W, H, instance_ids=[0, 1])
    with RGBDRenderer([mesh], W, H) as renderer, pytest.raises(ValueError, match="4x4 pose"):
        renderer.render(np.eye(3), K)


def test_depth_and_ids_are_exact_at_pixel_centres_on_a_tilted_plane() -> None:
    # Two coloured quads in the plane z = 0.3 x + 2 (camera frame = world frame, looking +z):
    # the left one (x < 0) instance 4, the right one unlabelled. The truth is analytic.
    def quad(x0: float, x1: float) -> trimesh.Trimesh:
        v = np.array([[x0, -3.0], [x1, -3.0], [x1, 3.0], [x0, 3.0]])
        verts = np.column_stack([v, 0.3 * v[:, 0] + 2.0])
        mesh = trimesh.Trimesh(verts, [[0, 1, 2], [0, 2, 3]], process=False)
        mesh.visual.face_colors = [200, 100, 50, 255]
        return mesh

    with RGBDRenderer([quad(-3.0, 0.0), quad(0.0, 3.0)], W, H, instance_ids=[4, -1]) as renderer:
        out = renderer.render(np.eye(4), K)
    u, _v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dx = (u - K[0, 2]) / K[0, 0]  # ray (dx, dy, 1) t meets z = 0.3 x + 2 at t = 2 / (1 - 0.3 dx)
    z = 2.0 / (1.0 - 0.3 * dx)
    np.testing.assert_allclose(out.depth.numpy(), z, rtol=1e-5)
    x = dx * z
    away = np.abs(x) > 1e-3  # the seam between the quads
    assert np.array_equal(out.instance_id.numpy()[away], np.where(x < 0, 4, -1)[away])
    assert bool(out.mask.all())
