"""The NeuS-style volume renderer against closed forms and the sphere tracer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from regnf.compositor import Camera, VolumeRendererConfig, look_at, render, render_volume
from regnf.render.volume_renderer import integrate
from tests.compositor import helpers as H
from tests.compositor.test_composite_field import make_composite
from tests.compositor.test_sphere_tracer import (
    HGT,
    WORLD_CENTER,
    WORLD_RADIUS,
    Empty,
    HalfNaN,
    W,
    boundary,
    composite_camera,
    sphere_camera,
    world_sphere,
)


def test_expected_depth_mask_and_normals_of_a_sphere() -> None:
    cam = sphere_camera()
    cfg = VolumeRendererConfig()
    out = render_volume(world_sphere(), cam, cfg)
    o, d = H.pixel_rays(cam.K, cam.camera_to_world, W, HGT)
    hit, t, miss = H.ray_sphere(o, d, WORLD_CENTER, WORLD_RADIUS)
    edge = boundary(miss, float(np.linalg.norm(cam.center - WORLD_CENTER)), cam)
    mask = out.mask.numpy().ravel()
    assert np.array_equal(mask[~edge], hit[~edge])

    forward = cam.camera_to_world[:3, 2]
    p = o + np.where(hit, t, 0.0)[:, None] * d
    n_true = (p - WORLD_CENTER) / WORLD_RADIUS
    frontal = hit & mask & (-np.einsum("ij,ij->i", n_true, d) > 0.2)
    err = np.abs(out.depth.numpy().ravel() - t * (d @ forward))[frontal]
    # A logistic density of width 1 / inv_s sampled every ~5 mm: looser than the tracer.
    assert float(np.median(err)) < 1e-3 and float(err.max()) < 2e-2
    normals = out.normals.numpy().reshape(-1, 3)
    assert float(np.einsum("ij,ij->i", normals[frontal], n_true[frontal]).min()) > 0.99
    ids = out.instance_id.numpy().ravel()
    assert bool((ids[mask] == 0).all() and (ids[~mask] == -1).all())
    assert bool((out.depth[~out.mask] == 0).all())
    # Every ray that crosses the bounds costs exactly the configured samples.
    evals = out.evals_per_pixel.numpy().ravel()
    assert set(np.unique(evals).tolist()) <= {0, cfg.n_samples}
    assert bool((evals[mask] == cfg.n_samples).all())
    assert int(out.lookups_per_pixel.sum()) == 0


def test_importance_samples_are_counted_and_do_not_hurt() -> None:
    cam = sphere_camera()
    base = render_volume(world_sphere(), cam, VolumeRendererConfig(n_samples=64))
    fine = render_volume(world_sphere(), cam, VolumeRendererConfig(n_samples=64, n_importance=32))
    o, d = H.pixel_rays(cam.K, cam.camera_to_world, W, HGT)
    hit, t, _ = H.ray_sphere(o, d, WORLD_CENTER, WORLD_RADIUS)
    truth = torch.as_tensor(t * (d @ cam.camera_to_world[:3, 2]), dtype=torch.float32).reshape(
        HGT, W
    )
    both = base.mask & fine.mask & torch.as_tensor(hit).reshape(HGT, W)
    e_base = (base.depth - truth)[both].abs().median()
    e_fine = (fine.depth - truth)[both].abs().median()
    assert float(e_fine) <= float(e_base) + 1e-5
    assert int(fine.evals_per_pixel.max()) == 96


def test_composite_ids_agree_with_the_sphere_tracer() -> None:
    field, cam = make_composite(), composite_camera()
    vol = render_volume(field, cam)
    st = render(field, cam)
    differ = int((vol.instance_id != st.instance_id).sum())
    assert differ <= 0.03 * W * HGT  # boundary pixels only
    assert {0, H.INSTANCE} <= set(vol.instance_id.unique().tolist())
    # The composite reports its own cost: 2 evaluations per sample inside the ball's box.
    assert int(vol.evals_per_pixel.max()) > VolumeRendererConfig().n_samples


def test_errors_and_empty_views() -> None:
    inside = Camera.from_fov(
        W, HGT, 60.0, look_at(H.PLACED_CENTER, H.PLACED_CENTER + [1.0, 0.0, 0.0])
    )
    with pytest.raises(ValueError, match="inside matter"):
        render_volume(make_composite(), inside)
    cam = Camera.from_fov(W, HGT, 50.0, look_at(np.array([0.0, -3.0, 0.5]), np.zeros(3)))
    with pytest.raises(ValueError, match="non-finite SDF"):
        render_volume(HalfNaN(0.5), cam, VolumeRendererConfig(n_samples=16))
    out = render_volume(
        Empty(), cam, VolumeRendererConfig(n_samples=16, background=(0.2, 0.2, 0.2))
    )
    assert not bool(out.mask.any()) and bool((out.instance_id == -1).all())
    assert torch.allclose(out.rgb, torch.full((HGT, W, 3), 0.2))
    with pytest.raises(ValueError, match="n_samples"):
        VolumeRendererConfig(n_samples=1)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        integrate(Empty(), torch.zeros(2, 3), torch.zeros(3, 3))


@pytest.mark.cuda
def test_volume_render_on_the_device_matches_the_closed_form(device: str) -> None:
    cam = sphere_camera()
    out = render_volume(world_sphere().to(device), cam, VolumeRendererConfig())
    assert out.depth.device.type == torch.device(device).type
    o, d = H.pixel_rays(cam.K, cam.camera_to_world, W, HGT)
    hit, t, miss = H.ray_sphere(o, d, WORLD_CENTER, WORLD_RADIUS)
    edge = boundary(miss, float(np.linalg.norm(cam.center - WORLD_CENTER)), cam)
    mask = out.mask.cpu().numpy().ravel()
    assert np.array_equal(mask[~edge], hit[~edge])
    p = o + np.where(hit, t, 0.0)[:, None] * d
    frontal = hit & mask & (-np.einsum("ij,ij->i", (p - WORLD_CENTER) / WORLD_RADIUS, d) > 0.2)
    err = np.abs(out.depth.cpu().numpy().ravel() - t * (d @ cam.camera_to_world[:3, 2]))[frontal]
    assert float(np.median(err)) < 1e-3 and float(err.max()) < 2e-2
