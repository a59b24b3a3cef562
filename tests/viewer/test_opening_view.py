"""The viewer's first image: the opening camera, its pre-rendered wide image cropped to each
browser's aspect, and requests that change nothing (no browser needed)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.cameras import look_at
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.scene_graph import add_instance, read_stage
from regnf.viewer.render_worker import (
    RenderWorker,
    ViewRequest,
    crop_to_aspect,
    opening_view,
    viewer_camera,
)
from regnf.viewer.viewer_config import ViewerConfig
from tests.scene_graph.helpers import make_stage, similarity


@pytest.fixture
def stage(tmp_path: Path) -> Path:
    path = make_stage(tmp_path, ("c", "t"))
    add_instance(path, "c", similarity(0.3, (0.8, 0.4, 0.0), 1.0), instance_id="c_1")
    add_instance(path, "t", similarity(0.0, (0.0, -1.0, 0.0), 1.0), instance_id="t_1")
    return path


@pytest.mark.parametrize("aspect", [1.0, 4 / 3, 1.7, 2.4])
def test_a_crop_of_the_wide_render_is_the_render_of_the_narrower_camera(stage: Path, aspect: float) -> None:
    comp = composite_from_stage(stage, StageCompositeConfig(mode="substitute"))
    # Every ray marched from its camera (no cones, whose tiles lie elsewhere in a crop): the
    # crop's pixels are then traced exactly as the narrower camera's, and must be its bits.
    sphere = dataclasses.replace(ViewerConfig().sphere, cone_tile=0)
    pose = look_at((3.0, -2.5, 2.0), (0.3, -0.3, 0.4))
    wide = ViewRequest(pose, 0.9, 2.4, "substitution", "rgb", 0)
    with torch.no_grad():
        image = render(comp.field, viewer_camera(wide, 72 * 30), sphere)
        crop = crop_to_aspect(image, aspect)
        assert crop is not None
        h, w = crop.rgb.shape[:2]
        assert abs(w / h - aspect) <= 2.0 / h  # the aspect, to the pixel
        # The camera a browser of that aspect has: same height and focal length, centred.
        f = 0.5 * h / math.tan(0.45)
        K = np.array([[f, 0.0, 0.5 * w], [0.0, f, 0.5 * h], [0.0, 0.0, 1.0]])
        direct = render(comp.field, Camera(K, w, h, pose), sphere)
    assert direct.mask.sum() > 0.2 * h * w, "the view shows too little to test"
    np.testing.assert_allclose(crop.rgb.numpy(), direct.rgb.numpy(), atol=1e-4)
    np.testing.assert_allclose(crop.depth.numpy(), direct.depth.numpy(), atol=1e-4)
    assert torch.equal(crop.instance_id, direct.instance_id)


def test_a_browser_wider_than_the_wide_render_gets_no_crop(stage: Path) -> None:
    comp = composite_from_stage(stage, StageCompositeConfig(mode="substitute"))
    req = ViewRequest(look_at((3.0, -2.5, 2.0), (0.0, 0.0, 0.4)), 0.9, 2.0, "substitution", "rgb", 0)
    with torch.no_grad():
        image = render(comp.field, viewer_camera(req, 40 * 20), ViewerConfig().sphere)
    assert crop_to_aspect(image, 2.5) is None


@pytest.mark.parametrize("blocked", ["nothing", "fill", "unseen"])
def test_the_opening_camera_stands_in_observed_free_space_and_looks_at_the_instances(
        stage: Path, blocked: str) -> None:
    from regnf.fields.analytic import Box, Union
    from regnf.observations.visibility import VisibilityGrid

    scene = read_stage(stage)  # its proxy: a 6 x 5 m floor
    target_truth = np.mean([(0.8, 0.4, 0.0), (0.0, -1.0, 0.0)], axis=0)
    room = [Box((3.0, 2.5, 0.05), (0.0, 0.0, -0.05))]  # the floor
    # The blocked half (x < 0) is the side the camera would look from first: towards the room's
    # centre from the instances.
    if blocked == "fill":  # a made-up fill over it
        room.append(Box((1.5, 2.5, 1.5), (-1.5, 0.0, 1.5)))
    field = Union(*room)
    if blocked == "unseen":  # no view saw it
        lo, hi = np.array([-3.0, -2.5, -0.2]), np.array([3.0, 2.5, 3.0])
        res = (30, 25, 16)
        centres = lo + (np.stack(np.meshgrid(*[np.arange(r) for r in res], indexing="ij"), -1) + 0.5) * (hi - lo) / res
        counts = torch.full(res, 255, dtype=torch.uint8)
        counts[torch.as_tensor(centres[..., 0] < 0.0)] = 0
        field.visibility = VisibilityGrid(counts, np.stack([lo, hi]))
    eye, target = opening_view(scene, field)
    lo, hi = scene.scene.proxy.extent
    assert np.all(eye[:2] >= lo[:2]) and np.all(eye[:2] <= hi[:2]) and eye[2] > target_truth[2]
    np.testing.assert_allclose(target, target_truth, atol=1e-9)
    assert np.linalg.norm(eye - target) > 1.0
    if blocked == "nothing":
        assert eye[0] < target_truth[0]  # towards the room's centre
    else:
        assert eye[0] > 0.1  # on the free, observed side
    # and the whole sight line is free
    line = eye + np.linspace(0.0, 0.8, 30)[:, None] * (target - eye)
    with torch.no_grad():
        assert float(field.sdf(torch.as_tensor(line, dtype=torch.float32)).min()) > 0.05


def test_a_request_that_shows_the_same_view_does_not_restart_the_render() -> None:
    # "proxies" requests are never rendered: the worker only keeps their versions.
    worker = RenderWorker(composites=None, config=ViewerConfig(), show=lambda *_: None)
    try:
        pose = look_at((3.0, -2.5, 2.0), (0.0, 0.0, 0.4))
        req = ViewRequest(pose, 0.9, 1.5, "proxies", "rgb", 0)
        worker.request(7, req)
        assert worker.current(7) == 1
        same = req._replace(camera_to_world=pose + 1e-7)  # float32 echo of the same camera
        worker.request(7, same)
        assert worker.current(7) == 1
        for changed in (req._replace(camera_to_world=look_at((3.0, -2.4, 2.0), (0.0, 0.0, 0.4))),
                        req._replace(aspect=1.6), req._replace(channel="depth"), req._replace(fov_y=1.0)):
            before = worker.current(7)
            worker.request(7, changed)
            assert worker.current(7) == before + 1
            worker.request(7, req)
    finally:
        worker.stop()
