"""``regnf render`` and ``regnf replace`` on a stage of tiny neural fields."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pxr import Usd, UsdGeom

from regnf.cli.app import main
from regnf.compositor import Camera
from regnf.compositor.replace import pick_replacements
from regnf.compositor.usd_cameras import camera_to_usd, write_cameras_usd
from regnf.core.file_lock import LOCK_NAME
from regnf.core.image_io import read_depth_png, read_instance_png, read_rgb_png
from regnf.scene_graph import add_instance, export_stage, read_stage
from tests.cli.cli_helpers import assert_fails
from tests.scene_graph.helpers import make_stage, similarity

VIEWS = ["--orbit", "3", "--orbit-radius", "4.5", "--width", "24", "--height", "18"]
"""Cameras well outside the tiny scene blob (radius ~1.5 m around (0, 0, 1.5))."""


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = make_stage(tmp_path_factory.mktemp("cli_render"), names=("c", "dc", "fc", "t"))
    add_instance(path, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(path, "dc", similarity(1.5, (-2.2, 0.4, 0.0), 1.0))
    add_instance(path, "t", similarity(-0.3, (0.3, 2.3, 0.0), 1.0))
    return path


def files(folder: Path) -> dict[str, str]:
    """Name -> sha256 of every file directly in ``folder`` but the lock file (it holds a pid)."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())
            if p.is_file() and p.name != LOCK_NAME}


@pytest.mark.parametrize("mode", ["scene", "substitute"])
def test_render_writes_every_view(stage: Path, tmp_path: Path, mode: str) -> None:
    out = tmp_path / mode
    assert main(["render", str(stage), "--composite.mode", mode, "--out", str(out), *VIEWS]) == 0
    expect = {f"{k}_{i:04d}.png" for k in ("rgb", "depth", "instance") for i in range(3)}
    assert set(files(out)) == expect | {"contact_sheet.png", "render.json"}
    data = json.loads((out / "render.json").read_text())
    assert data["mode"] == mode and len(data["cameras"]) == 3 and data["evals_per_pixel_mean"] > 0
    ids = set(np.unique(np.concatenate([read_instance_png(out / f"instance_{i:04d}.png").ravel() for i in range(3)])))
    if mode == "scene":
        assert data["instance_ids"] == {} and ids == {0}
    else:
        assert data["instance_ids"] == {"c_1": 1, "dc_1": 2, "t_1": 3} and ids <= {0, 1, 2, 3} and len(ids) > 1


def test_render_refuses_a_camera_inside_the_scene(stage: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bad"
    # A tight, steep orbit puts the cameras inside the scene blob.
    args = ["render", str(stage), "--composite.mode", "scene", "--out", str(out), "--orbit", "2",
            "--orbit-radius", "0.1", "--orbit-elevation", "85", "--width", "8", "--height", "6"]
    assert_fails(capsys, args, "camera 0 .*inside matter of the scene")
    assert not out.exists() or not any(out.rglob("*"))  # no image, no staging folder


def test_render_needs_cameras(stage: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert_fails(capsys, ["render", str(stage), "--composite.mode", "scene", "--out", str(tmp_path / "x")], r"--capture DIR, --orbit N or --usd-camera PRIM \[PRIM ...\] \(one of")


def cameras_of(out: Path) -> list[Camera]:
    """The cameras recorded in a render folder's render.json."""
    data = json.loads((out / "render.json").read_text())["cameras"]
    return [Camera(np.asarray(c["K"]), c["width"], c["height"], np.asarray(c["camera_to_world"])) for c in data]


def assert_same_view(a: Path, b: Path) -> None:
    """Two renders of one camera: equal up to USD's 32-bit focal length (an 8-bit step at most)."""
    rgb_a, rgb_b = read_rgb_png(a).astype(int), read_rgb_png(b).astype(int)
    assert np.abs(rgb_a - rgb_b).max() <= 1
    depth_a, depth_b = read_depth_png(a.with_name(a.name.replace("rgb", "depth"))), \
        read_depth_png(b.with_name(b.name.replace("rgb", "depth")))
    assert np.abs(depth_a - depth_b).max() <= 0.001


def test_render_from_usd_cameras(stage: Path, tmp_path: Path) -> None:
    orbit = tmp_path / "orbit"
    assert main(["render", str(stage), "--composite.mode", "scene", "--out", str(orbit), *VIEWS]) == 0
    cams = cameras_of(orbit)
    # From another stage, in the order given; the height follows from the aperture.
    write_cameras_usd(tmp_path / "cams.usda", cams)
    out = tmp_path / "usd"
    assert main(["render", str(stage), "--composite.mode", "scene", "--out", str(out), "--camera-stage",
                 str(tmp_path / "cams.usda"), "--usd-camera", "/Cameras/view_0002", "/Cameras/view_0000",
                 "--width", "24"]) == 0
    for got, want in zip(cameras_of(out), [cams[2], cams[0]], strict=True):
        assert (got.width, got.height) == (24, 18)
        np.testing.assert_allclose(got.camera_to_world, want.camera_to_world, atol=1e-9)
        np.testing.assert_allclose(got.K, want.K, rtol=1e-6)
    assert_same_view(out / "rgb_0000.png", orbit / "rgb_0002.png")
    assert_same_view(out / "rgb_0001.png", orbit / "rgb_0000.png")
    # From the rendered stage itself: a copy of the stage (beside its fields) holding a camera.
    own = stage.with_name("with_camera.usda")
    own.write_bytes(stage.read_bytes())
    usd = Usd.Stage.Open(str(own))
    camera_to_usd(usd, "/Cameras/hero", cams[1])
    usd.Save()
    out = tmp_path / "own"
    assert main(["render", str(own), "--composite.mode", "scene", "--out", str(out), "--usd-camera", "/Cameras/hero",
                 "--width", "24", "--height", "18"]) == 0
    assert_same_view(out / "rgb_0000.png", orbit / "rgb_0001.png")


def test_usd_camera_mistakes(stage: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x"
    args = ["render", str(stage), "--composite.mode", "scene", "--out", str(out)]
    assert_fails(capsys, [*args, "--usd-camera", "/Cameras/view_0000", *VIEWS], "one of them")
    assert_fails(capsys, [*args, "--camera-stage", str(stage), *VIEWS], "--camera-stage names the stage of the --usd-camera prims")
    assert_fails(capsys, [*args, "--usd-camera", "/Cameras/nope"], rf"regnf: cameras: {stage}: prim /Cameras/nope: no such prim")
    y_up = Usd.Stage.CreateNew(str(tmp_path / "y_up.usda"))
    UsdGeom.SetStageUpAxis(y_up, UsdGeom.Tokens.y)
    UsdGeom.Camera.Define(y_up, "/cam")
    y_up.Save()
    assert_fails(capsys, [*args, "--usd-camera", "/cam", "--camera-stage", str(tmp_path / "y_up.usda")], r"y_up.usda: prim /: upAxis is Y, expected Z")
    assert not out.exists()


def gif_frames(path: Path) -> int:
    with Image.open(path) as im:
        return im.n_frames


def test_render_and_replace_write_a_sequence(stage: Path, tmp_path: Path) -> None:
    out = tmp_path / "render"
    assert main(["render", str(stage), "--composite.mode", "substitute", "--out", str(out), *VIEWS,
                 "--render.sequence", "gif", "--render.sequence-fps", "5"]) == 0
    assert gif_frames(out / "sequence.gif") == 3
    assert json.loads((out / "render.json").read_text())["files"]["sequence"] == "sequence.gif"
    out = tmp_path / "replace"
    assert main(["replace", str(stage), "--seed", "5", "--out", str(out), *VIEWS, "--render.sequence", "gif"]) == 0
    assert gif_frames(out / "sequence.gif") == 3 and (out / "transforms.json").is_file()


def test_mp4_without_its_package_is_refused_at_once(stage: Path, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from regnf.compositor import sequence_io

    monkeypatch.setattr(sequence_io.importlib.util, "find_spec", lambda name: None)  # as if not installed
    for command in (["render", str(stage), "--composite.mode", "scene"], ["replace", str(stage)]):
        assert_fails(capsys, [*command, "--out", str(tmp_path / "x"), *VIEWS, "--render.sequence", "mp4"], "--render.sequence mp4: writing MP4 needs the package imageio-ffmpeg")
    assert not (tmp_path / "x").exists()


def test_replace_is_training_data_and_deterministic(stage: Path, tmp_path: Path) -> None:
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        assert main(["replace", str(stage), "--seed", "5", "--out", str(out), *VIEWS]) == 0
    a, b = files(outs[0]), files(outs[1])
    assert a.keys() == b.keys()
    differ = sorted(k for k in a if a[k] != b[k])
    assert differ == ["render.json"]  # only its timings and absolute paths differ
    data = json.loads((outs[0] / "transforms.json").read_text())
    assert (data["w"], data["h"]) == (24, 18) and data["fl_x"] == pytest.approx(data["fl_y"])
    assert len(data["frames"]) == 3
    cams = json.loads((outs[0] / "render.json").read_text())["cameras"]
    for frame, cam in zip(data["frames"], cams, strict=True):
        for key in ("file_path", "depth_file_path", "instance_file_path"):
            assert (outs[0] / frame[key]).is_file()
        M = np.asarray(frame["transform_matrix"])
        np.testing.assert_allclose(M, np.asarray(cam["camera_to_world"]) @ np.diag([1.0, -1.0, -1.0, 1.0]))
        np.testing.assert_allclose(M[:3, :3].T @ M[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(M[:3, :3]) == pytest.approx(1.0)
    # The layer swaps every chair for another chair; the only table stays.
    swapped = read_stage(outs[0] / "replacement.usda")
    chosen = {iid: inst.library_name for iid, inst in swapped.instances.items()}
    assert chosen == data["regnf"]["selections"] == pick_replacements(read_stage(stage), 5)
    assert chosen["c_1"] in ("dc", "fc") and chosen["dc_1"] in ("c", "fc") and chosen["t_1"] == "t"


def test_pick_replacements_depends_on_the_seed_only(stage: Path) -> None:
    scene = read_stage(stage)
    picks = [pick_replacements(scene, seed) for seed in range(12)]
    assert picks == [pick_replacements(scene, seed) for seed in range(12)]
    assert len({tuple(sorted(p.items())) for p in picks}) > 1
    for p in picks:
        for iid, name in p.items():
            assert scene.library[name].label == scene.library[scene.instances[iid].library_name].label


def test_replace_from_a_package_unpacks_it(stage: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    usdz = export_stage(stage, tmp_path / "pkg" / "room.usdz")
    out = tmp_path / "out"
    views = ["--orbit", "1", "--orbit-radius", "4.5", "--width", "12", "--height", "9"]
    assert main(["replace", str(usdz), "--seed", "5", "--out", str(out), *views]) == 0
    assert (out / "room.usda").is_file() and (out / "fields" / "c.safetensors").is_file()
    assert {i: s.library_name for i, s in read_stage(out / "replacement.usda").instances.items()} == \
        pick_replacements(read_stage(stage), 5)
    assert_fails(capsys, ["replace", str(usdz), "--seed", "6", "--out", str(out), *views], "already holds replacement.usda")


@pytest.mark.parametrize("command", ["render", "replace"])
def test_help_lists_every_render_and_composite_setting(command: str, capsys: pytest.CaptureFixture[str],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from regnf.compositor.render_folder import RenderConfig
    from regnf.compositor.stage_config import StageCompositeConfig
    from regnf.datasets.generate_config import SubstitutionConfig

    from .cli_help import assert_documented, help_text, leaf_settings

    text = help_text(command, capsys, monkeypatch)
    composite = StageCompositeConfig if command == "render" else SubstitutionConfig  # replace: no mode
    settings = leaf_settings(RenderConfig, "--render.") + leaf_settings(composite, "--composite.")
    assert len(settings) > 35  # both renderers, the folder, the composite
    assert_documented(settings, text)
