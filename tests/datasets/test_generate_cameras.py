"""``regnf generate --camera-source capture --capture DIR``: the views are a capture's own frames.

The capture is written here by hand (an sdfstudio ``meta_data.json`` with numpy, json and PIL,
not regnf's writer): ten frames around the test stage's room, each with its own ``K``
(fx != fy, the principal point off centre), stored in a normalised frame that
``worldtogt`` (a scale and a shift) takes to metres. The truths are those numbers: the views'
poses and intrinsics in ``transforms.json``, BOP's ``scene_camera.json`` and COCO's image
sizes, and the images of the single-variant path rendered from cameras built here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from regnf.cli.app import main
from regnf.compositor.cameras_io import OrbitConfig
from regnf.compositor.render_folder import RenderConfig
from regnf.compositor.replace import ReplaceConfig, replace_and_render
from regnf.core.executors import ExecutorConfig
from regnf.datasets.generate_source import source_summary
from regnf.datasets.generation import (
    GenerateConfig,
    _settings_key,
    generate,
    prepare_output,
)
from regnf.datasets.manifest import load_rows
from regnf.render.camera import Camera
from tests.datasets.test_generate import ORBIT, assert_same_images, config, stage  # noqa: F401 (a fixture)

FRAMES = 10
"""Frames of the test capture."""
SIZE = (40, 24)
"""Its image size (5:3)."""
WIDTH = 30
"""The data set's view width: the views are 30 x 18 (the capture's aspect ratio), K scaled by 3/4."""
SCALE, SHIFT = 2.0, np.array([0.5, -0.25, 0.1])
"""worldtogt: metres = SCALE * normalised + SHIFT."""
OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV camera axes -> nerfstudio's (OpenGL) ones."""


def looking_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) OpenCV camera-to-world (x right, y down, z forward) at ``eye`` looking at ``target``, +Z up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eye
    return pose


def write_capture(folder: Path, turn: float = 0.0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """An sdfstudio capture of FRAMES frames around the room; (poses in metres, K) per frame."""
    folder.mkdir(parents=True)
    w, h = SIZE
    poses, Ks, frames = [], [], []
    for i in range(FRAMES):
        a = turn + 2.0 * math.pi * i / FRAMES
        eye = np.array([4.5 * math.cos(a), 4.5 * math.sin(a), 1.5 + 0.1 * i])
        pose = looking_at(eye, np.array([0.2 * math.sin(i), 0.0, -0.3]))
        K = np.array([[30.0 + i, 0.0, 21.5 - 0.3 * i], [0.0, 27.0 + 0.5 * i, 11.0], [0.0, 0.0, 1.0]])
        normalised = pose.copy()
        normalised[:3, 3] = (pose[:3, 3] - SHIFT) / SCALE
        name = f"{i:06d}_rgb.png"
        Image.fromarray(np.full((h, w, 3), 20 * i, np.uint8)).save(folder / name)
        frames.append({"rgb_path": name, "camtoworld": normalised.tolist(), "intrinsics": K.tolist()})
        poses.append(pose)
        Ks.append(K)
    worldtogt = np.eye(4)
    worldtogt[:3, :3] *= SCALE
    worldtogt[:3, 3] = SHIFT
    meta = {"camera_model": "OPENCV", "width": w, "height": h, "worldtogt": worldtogt.tolist(),
            "scene_box": {"aabb": [[-2.0, -2.0, -1.0], [2.0, 2.0, 2.5]], "near": 0.05, "far": 8.0},
            "frames": frames}
    (folder / "meta_data.json").write_text(json.dumps(meta))
    return poses, Ks


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[np.ndarray], list[np.ndarray]]:
    folder = tmp_path_factory.mktemp("capture") / "cap"
    return (folder, *write_capture(folder))


def capture_config(folder: Path, n: int = 3, variants: int = 2, **kw) -> GenerateConfig:
    # cameras.height is not used with capture cameras: the views have the capture's aspect ratio.
    return GenerateConfig(variants=variants, cameras=OrbitConfig(n=n, width=WIDTH, height=99),
                          camera_source="capture", capture=folder,
                          executor=ExecutorConfig(kind="local", workers=2), **kw)


def scaled(K: np.ndarray) -> np.ndarray:
    return np.diag([WIDTH / SIZE[0], WIDTH / SIZE[0], 1.0]) @ K


def test_the_views_are_the_capture_s_frames(stage: Path, capture: tuple, tmp_path: Path) -> None:  # noqa: F811
    folder, poses, Ks = capture
    out = tmp_path / "data"
    cfg = capture_config(folder, format="nerfstudio,coco,bop", jitter_cameras=False)
    report = generate(stage, out, cfg, progress=False)
    assert report.made == [0, 1] and not report.failed
    chosen = [0, 5, 9]  # three frames evenly spaced over 0..9, the same in every variant
    rows = load_rows(out)
    assert [r["capture_frames"] for r in rows] == [chosen, chosen]
    for r in rows:
        variant = out / r["variant"]
        tj = json.loads((variant / "transforms.json").read_text())
        assert tj["regnf"]["capture_frames"] == chosen
        for frame, i in zip(tj["frames"], chosen, strict=True):
            assert (frame["w"], frame["h"]) == (30, 18)
            K = scaled(Ks[i])
            assert [frame[k] for k in ("fl_x", "fl_y", "cx", "cy")] == pytest.approx(
                [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], abs=1e-9)
            np.testing.assert_allclose(frame["transform_matrix"], poses[i] @ OPENGL, atol=1e-9)
        for k in range(3):
            assert Image.open(variant / f"rgb_{k:04d}.png").size == (30, 18)
        bop_cams = json.loads((out / "bop" / "train" / f"{r['seed']:06d}" / "scene_camera.json").read_text())
        for k, i in enumerate(chosen):
            cam = bop_cams[str(k)]
            np.testing.assert_allclose(np.reshape(cam["cam_K"], (3, 3)), scaled(Ks[i]), atol=1e-9)
            R, t = poses[i][:3, :3], poses[i][:3, 3]
            np.testing.assert_allclose(np.reshape(cam["cam_R_w2c"], (3, 3)), R.T, atol=1e-9)
            np.testing.assert_allclose(cam["cam_t_w2c"], -1000.0 * R.T @ t, atol=1e-6)
    coco = json.loads((out / "coco" / "annotations.json").read_text())
    assert len(coco["images"]) == 6 and {(im["width"], im["height"]) for im in coco["images"]} == {(30, 18)}
    record = json.loads((out / "generation.json").read_text())
    assert record["settings"]["camera_source"] == "capture" and record["settings"]["cameras"]["height"] == 18
    assert record["capture"]["path"] == str(folder) and record["capture"]["frames"] == FRAMES

    # The images are the ones the single-variant path renders from the capture's cameras built here.
    cams = [Camera(scaled(Ks[i]), 30, 18, poses[i]) for i in chosen]
    result = replace_and_render(stage, 1, tmp_path / "one", cams, ReplaceConfig())
    assert result.selections == rows[1]["selections"]
    assert_same_images(tmp_path / "one", out / rows[1]["variant"], 3)


def test_each_seed_takes_its_own_frames_and_a_run_resumes_with_the_same_capture(
        stage: Path, capture: tuple, tmp_path: Path) -> None:  # noqa: F811
    folder, poses, _ = capture
    out = tmp_path / "data"
    first = generate(stage, out, capture_config(folder, n=4, variants=2), progress=False)
    assert first.made == [0, 1]
    # The same capture at another path is the same data set: the run resumes.
    moved = tmp_path / "moved"
    shutil.copytree(folder, moved)
    rest = generate(stage, out, capture_config(moved, n=4, variants=3), progress=False)
    assert rest.skipped == [0, 1] and rest.made == [2] and not rest.problems
    rows = load_rows(out)
    sets = [r["capture_frames"] for r in rows]
    for frames in sets:
        assert frames == sorted(set(frames)) and len(frames) == 4 and 0 <= frames[0] and frames[-1] < FRAMES
    assert len({tuple(f) for f in sets}) >= 2, "every seed took the same frames"
    for r in rows:  # the views are the recorded frames
        tj = json.loads((out / r["variant"] / "transforms.json").read_text())
        for frame, i in zip(tj["frames"], r["capture_frames"], strict=True):
            np.testing.assert_allclose(frame["transform_matrix"], poses[i] @ OPENGL, atol=1e-9)

    # The same seed in another run takes the same frames.
    again = tmp_path / "again"
    generate(stage, again, capture_config(folder, n=4, variants=1, first_seed=2), progress=False)
    assert load_rows(again)[0]["capture_frames"] == sets[2]

    # Another capture (the same frames turned) into the same folder is refused, before any work.
    other = tmp_path / "other"
    write_capture(other, turn=0.3)
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    with pytest.raises(ValueError, match="generation.json.*another capture"):
        generate(stage, out, capture_config(other, n=4, variants=3), progress=False)
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before


@pytest.mark.parametrize("case", ["no capture", "missing", "not a capture", "too few frames", "capture alone"])
def test_a_bad_capture_is_one_line_and_nothing_is_written(stage: Path, capture: tuple, tmp_path: Path,  # noqa: F811
                                                          capsys: pytest.CaptureFixture[str], case: str) -> None:
    folder = capture[0]
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("not a capture")
    options, named = {
        "no capture": (["--camera-source", "capture"], "--capture DIR"),
        "missing": (["--camera-source", "capture", "--capture", str(tmp_path / "nowhere")], str(tmp_path / "nowhere")),
        "not a capture": (["--camera-source", "capture", "--capture", str(empty)], str(empty)),
        "too few frames": (["--camera-source", "capture", "--capture", str(folder), "--cameras.n", "11"],
                           str(folder / "meta_data.json")),
        "capture alone": (["--capture", str(folder)], "--camera-source capture"),
    }[case]
    out = tmp_path / "data"
    capsys.readouterr()
    assert main(["generate", str(stage), "--out", str(out), "--variants", "1", "--cameras.width", str(WIDTH),
                 *options]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err, err
    assert not out.exists()


def test_an_orbit_data_set_keeps_its_settings_and_key(stage: Path, tmp_path: Path) -> None:  # noqa: F811
    """Data sets made before capture cameras resume: the orbit's settings have no new key, and
    the config_key is the settings and the source alone, as before."""
    settings = GenerateConfig().output_settings()
    assert sorted(settings) == ["appearance", "cameras", "composite", "device", "formats", "jitter_cameras",
                                "render", "threads_per_task"]
    assert GenerateConfig(camera_source="orbit").output_settings() == settings
    cfg = config(n=1)
    _, key = prepare_output(stage, tmp_path / "data", cfg)
    assert key == _settings_key({"settings": cfg.output_settings(), "source": source_summary(stage)})
    record = json.loads((tmp_path / "data" / "generation.json").read_text())
    assert sorted(record) == ["base_stage", "config_key", "settings", "source", "source_stage"]


def test_the_baked_renderer_bakes_for_the_capture_s_pixel_footprint(stage: Path, capture: tuple,  # noqa: F811
                                                                   tmp_path: Path) -> None:
    """The grids' cells come from the capture's views (not the orbit's) and the variant renders from them."""
    from regnf.compositor.baked_composite import masked_scene
    from regnf.compositor.from_stage import composite_from_stage
    from regnf.compositor.stage_config import StageCompositeConfig
    from regnf.datasets.data_set_grids import load_data_set_grids
    from regnf.render.baked_field import bake_cell, grid_nodes

    folder, poses, Ks = capture
    cfg = capture_config(folder, n=2, variants=1, render=RenderConfig(renderer="baked", progress=False))
    report = generate(stage, tmp_path / "data", cfg, progress=False)
    assert report.made == [0] and report.bake_seconds > 0
    grids = load_data_set_grids(tmp_path / "data" / "baked" / "index.json")
    scene = masked_scene(composite_from_stage(stage, StageCompositeConfig(mode="substitute")).field)
    every = [Camera(scaled(Ks[i]), 30, 18, poses[i]) for i in range(FRAMES)]  # jittered: any frame
    bake = cfg.render.bake

    def nodes(cams: list[Camera]) -> list[int]:
        return list(grid_nodes(scene.bounds, bake_cell(scene, cams, bake), bake.coarse_stride))

    orbit = dataclasses.replace(cfg, camera_source="orbit", capture=None, cameras=ORBIT)
    assert nodes(every) != nodes(orbit_cameras(stage, orbit))  # the test tells them apart
    assert grids.scene.info.provenance["baked"]["nodes"] == nodes(every)


def orbit_cameras(stage_file: Path, cfg: GenerateConfig) -> list[Camera]:
    from regnf.compositor.cameras_io import field_bounds_metres, orbit_around_bounds
    from regnf.compositor.from_stage import composite_from_stage
    from regnf.compositor.stage_config import StageCompositeConfig

    bounds = field_bounds_metres(composite_from_stage(stage_file, StageCompositeConfig(mode="scene")).field.scene)
    return orbit_around_bounds(bounds, cfg.cameras)
