"""Composites from USD stages: frames by hand, removal regions, replacement layers, packages."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from regnf.compositor import Camera, look_at, render
from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.regions import OrientedBoxRegion, ShellRegion
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.compositor.substitution import base_height, check_z_up, library_to_scene
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDF
from regnf.io.checkpoint import save_field
from regnf.scene_graph import (
    StageError,
    add_instance,
    add_instance_from_registration,
    export_stage,
    make_replacement_layer,
    new_stage,
    original_selections,
    read_stage,
)
from tests.scene_graph.helpers import TINY, box_proxy, make_stage, registration_json, similarity

from . import golden_scenes as G

O_C = similarity(0.5, (1.0, -0.5, 0.0), 1.2)
"""Instance c_1: yaw 0.5 rad, at (1, -0.5, 0) m, 20 % larger than the library object."""


def rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Helper fields: scene to_world = 3 I + (0, 0, 1.5); library to_world = 0.6 I + (0, 0, 0.3)."""
    path = make_stage(tmp_path_factory.mktemp("fs"))
    add_instance(path, "c", O_C)
    add_instance(path, "t", similarity(-0.3, (-1.0, 0.8, 0.0), 1.0))
    return path


def test_library_to_scene_by_hand() -> None:
    S = np.diag([2.0, 2.0, 2.0, 1.0])
    S[:3, 3] = (1.0, 2.0, 0.5)
    O = np.eye(4)
    O[:3, :3] = 1.5 * rz(math.pi / 2)
    O[:3, 3] = (3.0, 0.0, 0.0)
    L = np.diag([0.5, 0.5, 0.5, 1.0])
    L[:3, 3] = (0.0, 0.0, 0.25)
    # By hand: a library point y is 0.5 y + (0, 0, 0.25) m on the object, turned by 90 deg,
    # scaled by 1.5 and moved by (3, 0, 0) into the room, then (x - (1, 2, 0.5)) / 2.
    expected = np.eye(4)
    expected[:3, :3] = 0.375 * rz(math.pi / 2)
    expected[:3, 3] = (1.0, -1.0, -0.0625)
    np.testing.assert_allclose(library_to_scene(S, O, L), expected, atol=1e-12)
    np.testing.assert_allclose(library_to_scene(S, O, L) @ [1.0, 0.0, 0.0, 1.0], [1.0, -0.625, -0.0625, 1.0])
    assert base_height(S, O) == pytest.approx(-0.25)  # the canonical origin at z = 0 m


def test_frames_and_removal_box_from_a_stage(stage: Path) -> None:
    comp = composite_from_stage(stage, StageCompositeConfig(box_pad=0.05, floor_margin=0.01))
    assert comp.instance_ids == {"c_1": 1, "t_1": 2}
    assert comp.field.instance_ids == (1, 2)
    # By hand: inv(S) O L with S = 3 I + (0, 0, 1.5) and L = 0.6 I + (0, 0, 0.3):
    # linear 0.6 * 1.2 / 3 Rz(0.5); translation (O (0, 0, 0.3) - (0, 0, 1.5)) / 3.
    M = comp.field.placements[0].mapped.matrix.numpy()
    np.testing.assert_allclose(M[:3, :3], 0.24 * rz(0.5), atol=1e-12)
    np.testing.assert_allclose(M[:3, 3], [1.0 / 3.0, -0.5 / 3.0, (0.36 - 1.5) / 3.0], atol=1e-12)
    assert comp.field.scale_of(1) == pytest.approx(0.24)
    # Removal: the library bounds [-1, 1]^3 mapped (half 0.24) and grown by 5 %, the floor
    # spared below the base (canonical z = 0 -> scene field z = -0.5) plus 1 cm (1/3 cm units).
    region = comp.field.removals[0]
    assert isinstance(region, OrientedBoxRegion)
    np.testing.assert_allclose(region.box.center, M[:3, 3], atol=1e-12)
    np.testing.assert_allclose(region.box.half_extents, [0.252] * 3, atol=1e-12)
    np.testing.assert_allclose(region.box.rotation, rz(0.5), atol=1e-12)
    assert region.keep_floor == pytest.approx(-0.5) and region.floor_margin == pytest.approx(0.01 / 3.0)
    c = M[:3, 3]
    pts = torch.tensor(np.array([c, [c[0], c[1], -0.5 - 0.001], [c[0], c[1], -0.5 + 0.002],
                                 [c[0], c[1], -0.5 + 0.01]]))
    m = region.sdf(pts).numpy()
    assert m[0] < 0 and m[3] < 0  # inside the object's box: removed
    assert m[1] > 0 and m[2] > 0  # the floor under it (and 1 cm above) stays


def test_scene_mode_is_the_scene_alone(stage: Path) -> None:
    comp = composite_from_stage(stage, StageCompositeConfig(mode="scene"))
    assert comp.instance_ids == {} and len(comp.field.placements) == 0 and len(comp.field.removals) == 0
    x = torch.rand(64, 3) * 2 - 1
    torch.testing.assert_close(comp.field.sdf(x), comp.field.scene.sdf(x))


def test_replacement_removes_the_registered_object_and_shows_the_new(tmp_path: Path) -> None:
    path = make_stage(tmp_path, names=("c", "dc", "t"))
    ckpt = path.parent / "fields" / "c.safetensors"
    add_instance_from_registration(path, registration_json("c", ckpt, O_C))  # registered as c
    add_instance(path, "c", similarity(2.0, (-1.0, 1.0, 0.0), 1.0), instance_id="hand")  # no provenance
    layer = make_replacement_layer(path, {"c_1": "dc", "hand": "dc"}, path.parent / "swap.usda")
    assert original_selections(layer, read_stage(layer)) == {"c_1": "c", "hand": "c"}
    comp = composite_from_stage(layer, StageCompositeConfig(removal="shell"))
    shown = [p.field.name for p in comp.field.placements]
    removed = [r.placement.field.name for r in comp.field.removals]
    assert shown == ["dc", "dc"] and removed == ["c", "c"]
    assert all(isinstance(r, ShellRegion) for r in comp.field.removals)
    # Box removal adds the registration's proposal box (scene field frame) for c_1 only.
    boxes = composite_from_stage(layer, StageCompositeConfig(removal="box", box_pad=0.0)).field.removals
    assert len(boxes) == 3
    np.testing.assert_allclose(boxes[1].box.center, [1.0, 2.0, 0.4])
    np.testing.assert_allclose(boxes[1].box.half_extents, [0.3, 0.3, 0.45])


def test_a_package_composes_like_its_stage(stage: Path, tmp_path: Path) -> None:
    usdz = export_stage(stage, tmp_path / "pkg" / "room.usdz")
    a = composite_from_stage(stage).field
    b = composite_from_stage(usdz).field
    cam = Camera.from_fov(24, 18, 60.0, look_at((5.0, -4.0, 3.0), (0.0, 0.0, 0.5)))
    ra, rb = render(a, cam), render(b, cam)
    assert torch.equal(ra.depth, rb.depth) and torch.equal(ra.instance_id, rb.instance_id)
    np.testing.assert_array_equal(a.placements[1].mapped.matrix.numpy(), b.placements[1].mapped.matrix.numpy())


def test_a_missing_checkpoint_names_the_file(tmp_path: Path) -> None:
    path = make_stage(tmp_path)
    add_instance(path, "c", O_C)
    (path.parent / "fields" / "c.safetensors").unlink()
    with pytest.raises(StageError, match=r"c\.safetensors"):
        composite_from_stage(path)


def test_a_tilted_scene_frame_is_refused_for_substitution(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    tilted = similarity(0.0, (0.0, 0.0, 1.5), 3.0, tilt=0.2)
    scene = NeuralSDF(TINY, to_world=torch.as_tensor(tilted), info=FieldInfo(label="scene", name="room"))
    save_field(scene, src / "room.safetensors")
    lib = NeuralSDF(TINY, to_world=torch.as_tensor(similarity(0.0, (0, 0, 0.3), 0.6)),
                    info=FieldInfo(label="chair", name="c"))
    save_field(lib, src / "c.safetensors")
    path = tmp_path / "stage" / "room.usda"
    new_stage(path, src / "room.safetensors", [src / "c.safetensors"],
              proxies={"scene": box_proxy((3.0, 3.0, 0.1)), "c": box_proxy((0.4, 0.4, 0.8))})
    add_instance(path, "c", O_C)
    assert composite_from_stage(path, StageCompositeConfig(mode="scene")).instance_ids == {}
    with pytest.raises(StageError, match=r"/World/Scene.*\+Z"):
        composite_from_stage(path)
    with pytest.raises(ValueError, match="z axis"):
        check_z_up(tilted)


def test_substituting_each_object_by_itself_keeps_the_geometry() -> None:
    """Analytic: with library colours matching, the substitute is the scene (signs agree)."""
    scene = G.scene_field(match_library=True)
    comp = G.composite("own", StageCompositeConfig(), match_library=True)
    rng = np.random.default_rng(3)
    world = rng.uniform([-1.5, -1.3, -0.1], [1.5, 1.3, 1.2], size=(20000, 3))
    x = torch.as_tensor((world - G.S[:3, 3]) @ np.linalg.inv(G.S[:3, :3]).T)
    a, b = scene.sdf(x), comp.sdf(x)
    near = a.abs() < 0.005  # within 8 mm of a surface the composite is a bound, not exact
    assert int((~near).sum()) > 15000 and int((a < 0).sum()) > 500  # it sees matter and space
    assert bool((torch.sign(a) == torch.sign(b))[~near].all())
