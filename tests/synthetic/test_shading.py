"""Baked Lambertian shading."""

from __future__ import annotations

import numpy as np
import trimesh

from regnf.synthetic.shading import ShadingConfig, shade_face_colors, shaded_copy


def test_lambert_terms() -> None:
    cfg = ShadingConfig(light_dir=(0.0, 0.0, 2.0), ambient=0.4, diffuse=0.5)
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    albedo = np.full((4, 4), 200, dtype=np.uint8)
    out = shade_face_colors(normals, albedo, cfg)
    assert out.dtype == np.uint8 and out.shape == (4, 4)
    np.testing.assert_array_equal(out[:, 0], np.round(200 * np.array([0.9, 0.4, 0.4, 0.8])))
    np.testing.assert_array_equal(out[:, 3], 200)  # alpha kept


def test_shaded_copy_leaves_the_input_alone() -> None:
    mesh = trimesh.creation.box((1, 1, 1))
    mesh.visual.face_colors = [100, 150, 200, 255]
    shaded = shaded_copy(mesh)
    assert np.all(mesh.visual.face_colors[:, :3] == [100, 150, 200])
    top = mesh.face_normals[:, 2] > 0.9
    bottom = mesh.face_normals[:, 2] < -0.9
    assert np.all(shaded.visual.face_colors[top, 0] > shaded.visual.face_colors[bottom, 0])
    # The bottom only gets the ambient term.
    np.testing.assert_array_equal(shaded.visual.face_colors[bottom, 0], round(100 * 0.45))
