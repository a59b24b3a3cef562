"""Rendering many views into a folder: files, report, nothing partial on failure; contact sheets
and nerfstudio's transforms.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import regnf.compositor.render_folder as RV
from regnf.compositor import Camera, look_at
from regnf.compositor.cameras_io import OrbitConfig, orbit_around_bounds
from regnf.compositor.contact_sheets import contact_sheet
from regnf.compositor.nerfstudio import opencv_to_opengl, transforms_json
from regnf.compositor.render_folder import RenderConfig, ViewFiles, render_views
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.file_lock import LOCK_NAME
from regnf.core.image_io import read_depth_png, read_instance_png, read_rgb_png

from . import golden_scenes as G

QUIET = RenderConfig(progress=False)


def cameras(n: int, width: int = 24, height: int = 18) -> list[Camera]:
    return orbit_around_bounds(np.array([[-1.6, -1.4, 0.0], [1.6, 1.4, 1.2]]),
                               OrbitConfig(n=n, width=width, height=height, radius=2.2, elevation_deg=35.0))


def test_views_report_and_sheet(tmp_path: Path) -> None:
    field = G.composite("own", StageCompositeConfig())
    cams = cameras(3)
    report = render_views(field, cams, tmp_path / "out", QUIET, {"stage": "golden"})
    out = tmp_path / "out"
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"{k}_{i:04d}.png" for k in ("rgb", "depth", "instance") for i in range(3)]
                           + ["contact_sheet.png", "render.json", LOCK_NAME])  # and no staging folder left
    data = json.loads((out / "render.json").read_text())
    assert data["stage"] == "golden" and data["renderer"] == "sphere"
    assert len(data["cameras"]) == 3 and data["cameras"][1]["width"] == 24
    np.testing.assert_allclose(data["cameras"][2]["camera_to_world"], cams[2].camera_to_world)
    assert data["evals_per_pixel_mean"] == pytest.approx(report.evals_per_pixel_mean) and report.evals_per_pixel_mean > 1
    assert data["renderer_config"]["far"] is None  # inf is not JSON: written as null
    assert set(data["timings"]) >= {"render_seconds_total", "per_view_seconds_mean", "distance_grid_seconds"}
    ids = read_instance_png(out / "instance_0000.png")
    assert set(np.unique(ids).tolist()) <= {0, 1, 2} and {1, 2} & set(np.unique(ids).tolist())
    depth = read_depth_png(out / "depth_0000.png")
    assert (depth[ids > 0] > 0).all() and depth.max() < 5.0
    sheet = read_rgb_png(out / "contact_sheet.png")
    assert sheet.shape == (2 + 2 * (18 + 2), 2 + 2 * (24 + 2), 3)  # 2 x 2 tiles for 3 views
    np.testing.assert_array_equal(sheet[2:20, 28:52], read_rgb_png(out / "rgb_0001.png"))


def test_a_camera_inside_matter_writes_nothing(tmp_path: Path) -> None:
    field = G.composite("own", StageCompositeConfig())
    inside = Camera.from_fov(24, 18, 60.0, look_at((0.0, 0.0, -0.02), (1.0, 0.0, -0.02)))  # in the floor
    with pytest.raises(ValueError, match=r"camera 2 .*inside matter"):
        render_views(field, [*cameras(2), inside], tmp_path / "out", QUIET)
    assert not (tmp_path / "out").exists()  # cameras are checked before anything is made


def test_a_failure_midway_leaves_the_folder_as_it_was(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    field = G.composite("own", StageCompositeConfig())
    out = tmp_path / "out"
    render_views(field, cameras(3), out, QUIET)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real = RV.render_batch
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("field returned a non-finite SDF")
        return real(*args, **kwargs)

    monkeypatch.setattr(RV, "render_batch", failing)
    with pytest.raises(ValueError, match="non-finite"):
        render_views(G.composite("other", StageCompositeConfig()), cameras(3), out,
                     RenderConfig(progress=False, overwrite=True, views_per_trace=1))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # no staging folder, no new image


def test_overwriting_needs_consent_and_drops_stale_views(tmp_path: Path) -> None:
    field = G.composite("own", StageCompositeConfig(mode="scene"))
    out = tmp_path / "out"
    render_views(field, cameras(3), out, QUIET)
    with pytest.raises(ValueError, match="already holds a render"):
        render_views(field, cameras(2), out, QUIET)
    render_views(field, cameras(2), out, RenderConfig(progress=False, overwrite=True))
    assert not (out / "rgb_0002.png").exists() and (out / "rgb_0001.png").exists()
    assert len(json.loads((out / "render.json").read_text())["views"]) == 2


def test_volume_renderer_writes_the_same_files(tmp_path: Path) -> None:
    from regnf.compositor import VolumeRendererConfig

    cfg = RenderConfig(renderer="volume", volume=VolumeRendererConfig(n_samples=64), progress=False)
    report = render_views(G.composite("own", StageCompositeConfig()), cameras(1), tmp_path, cfg)
    assert report.views == [ViewFiles("rgb_0000.png", "depth_0000.png", "instance_0000.png")]
    assert json.loads((tmp_path / "render.json").read_text())["renderer_config"]["n_samples"] == 64


def test_baked_renderer_writes_the_same_files_and_images_close_to_the_sphere_tracers(tmp_path: Path) -> None:
    # 64 x 48: the grids' cells follow the pixel footprint, so a thumbnail gets coarse ones.
    field, cams = G.composite("own", StageCompositeConfig()), cameras(2, 64, 48)
    render_views(field, cams, tmp_path / "sphere", QUIET)
    report = render_views(field, cams, tmp_path / "baked", RenderConfig(renderer="baked", progress=False))
    assert [v.rgb for v in report.views] == ["rgb_0000.png", "rgb_0001.png"]
    data = json.loads((tmp_path / "baked" / "render.json").read_text())
    assert data["renderer"] == "baked" and data["renderer_config"]["bake"]["cell_pixels"] == 0.5
    assert data["timings"]["bake_seconds"] > 0
    for k in range(2):
        exact, baked = (read_instance_png(tmp_path / d / f"instance_{k:04d}.png") for d in ("sphere", "baked"))
        assert (exact == baked).mean() > 0.98
        rgb = [read_rgb_png(tmp_path / d / f"rgb_{k:04d}.png").astype(float) for d in ("sphere", "baked")]
        same = exact == baked
        assert np.median(np.abs(rgb[0] - rgb[1]).max(axis=-1)[same]) <= 1.0


def test_the_grids_settings_are_a_data_set_setting_of_the_baked_renderer_only() -> None:
    from regnf.datasets.generation import GenerateConfig

    # They change no file of a sphere-traced data set, so they stay out of its settings key
    # (a data set made before them still resumes).
    assert "bake" not in GenerateConfig().output_settings()["render"]
    baked = GenerateConfig(render=RenderConfig(renderer="baked")).output_settings()["render"]
    assert baked["bake"]["cell_pixels"] == 0.5


def test_contact_sheet_layout() -> None:
    imgs = [np.full((10, 20, 3), 40 * k, dtype=np.uint8) for k in range(5)]
    sheet = contact_sheet(imgs, gap=1)
    assert sheet.shape == (1 + 2 * 11, 1 + 3 * 21, 3)
    assert (sheet[12:22, 22:42] == 160).all()  # the 5th image: row 1, column 1
    small = contact_sheet([np.zeros((40, 80, 3), np.uint8)], tile_width=20, gap=0)
    assert small.shape == (10, 20, 3)
    with pytest.raises(ValueError, match="uint8"):
        contact_sheet([np.zeros((4, 4, 3))])


def test_transforms_json_uses_opengl_poses() -> None:
    cam = Camera.from_fov(40, 30, 60.0, look_at((2.0, -1.0, 1.5), (0.0, 0.0, 0.3)))
    gl = opencv_to_opengl(cam.camera_to_world)
    # OpenGL cameras look along -z with +y up: -z points at the target, +y has a +Z component.
    to_target = np.array([0.0, 0.0, 0.3]) - cam.center
    np.testing.assert_allclose(-gl[:3, 2], to_target / np.linalg.norm(to_target), atol=1e-12)
    assert gl[2, 1] > 0
    np.testing.assert_array_equal(gl[:3, 3], cam.center)
    files = [ViewFiles("rgb_0000.png", "depth_0000.png", "instance_0000.png")] * 2
    shared = transforms_json([cam, cam], files, {"seed": 1})
    assert shared["fl_x"] == pytest.approx(cam.K[0, 0]) and shared["w"] == 40 and shared["h"] == 30
    assert shared["frames"][0]["instance_file_path"] == "instance_0000.png"
    assert "mask_path" not in shared["frames"][0]  # nerfstudio would leave out the room's pixels and shared["regnf"] == {"seed": 1}
    other = Camera(cam.K * np.array([[2.0], [2.0], [1.0]]), 80, 60, cam.camera_to_world)
    mixed = transforms_json([cam, other], files)
    assert "fl_x" not in mixed and mixed["frames"][1]["w"] == 80 and mixed["frames"][1]["fl_x"] == pytest.approx(2 * cam.K[0, 0])


def test_files_no_render_wrote_are_never_written_over_or_removed(tmp_path: Path) -> None:
    field = G.composite("own", StageCompositeConfig(mode="scene"))
    out = tmp_path / "out"
    out.mkdir()
    (out / "rgb_0001.png").write_bytes(b"the user's own frame")
    with pytest.raises(ValueError, match=r"rgb_0001.png: exists and was not written by a render into this folder"):
        render_views(field, cameras(2), out, RenderConfig(progress=False, overwrite=True))
    assert sorted(p.name for p in out.iterdir()) == ["rgb_0001.png"]  # refused before anything was made
    (out / "rgb_0001.png").unlink()
    render_views(field, cameras(3), out, QUIET)
    (out / "rgb_0007.png").write_bytes(b"added by the user")  # no render.json lists it
    render_views(field, cameras(2), out, RenderConfig(progress=False, overwrite=True))
    assert not (out / "rgb_0002.png").exists()  # the earlier render's, listed in its render.json
    assert (out / "rgb_0007.png").read_bytes() == b"added by the user"


def test_a_view_larger_than_the_limit_is_refused_before_rendering(tmp_path: Path) -> None:
    field = G.composite("own", StageCompositeConfig(mode="scene"))
    huge = Camera.from_fov(4097, 4096, 60.0, cameras(1)[0].camera_to_world)
    with pytest.raises(ValueError, match=r"camera 1: a view of 4097 x 4096 pixels is more than the 16,777,216"):
        render_views(field, [*cameras(1), huge], tmp_path / "out", QUIET)
    assert not (tmp_path / "out").exists()


def assert_same_views(a: Path, b: Path, n: int) -> None:
    """The first ``n`` views' RGB, depth and instance PNGs of render folders ``a`` and ``b`` are the same bytes."""
    for k in range(n):
        for kind in ("rgb", "depth", "instance"):
            assert (a / f"{kind}_{k:04d}.png").read_bytes() == (b / f"{kind}_{k:04d}.png").read_bytes(), (kind, k)


@pytest.mark.parametrize("views_per_trace", [1, 2])
def test_views_side_by_side_are_the_images_of_one_after_another(tmp_path: Path, views_per_trace: int) -> None:
    field = G.composite("own", StageCompositeConfig())
    cams = cameras(3)
    for workers in (1, 2):
        render_views(field, cams, tmp_path / str(workers),
                     RenderConfig(progress=False, workers=workers, views_per_trace=views_per_trace))
    assert_same_views(tmp_path / "1", tmp_path / "2", 3)
    with pytest.raises(ValueError, match="workers"):
        RenderConfig(workers=0)


def test_views_traced_together_are_the_views_traced_alone(tmp_path: Path) -> None:
    # An analytic composite: a ray's trace is its own, so batching changes no bit.
    field = G.composite("own", StageCompositeConfig())
    cams = [*cameras(2), *cameras(2, width=30, height=20)]
    for per in (1, 4):
        render_views(field, cams, tmp_path / str(per), RenderConfig(progress=False, views_per_trace=per))
    assert_same_views(tmp_path / "1", tmp_path / "4", 4)
    with pytest.raises(ValueError, match="views_per_trace"):
        RenderConfig(views_per_trace=0)


def test_view_batches_are_consecutive_and_bounded() -> None:
    small, big = cameras(1)[0], Camera.from_fov(1024, 1024, 60.0, cameras(1)[0].camera_to_world)
    assert RV.view_batches([small] * 7, 3) == [[0, 1, 2], [3, 4, 5], [6]]
    assert RV.view_batches([small] * 2, 1) == [[0], [1]]
    assert RV.TRACE_PIXELS == 1024 * 1024  # so that a 1024 x 1024 view fills a batch alone
    assert RV.view_batches([small, big, small, small], 3) == [[0], [1], [2, 3]]
    assert RV.view_batches([], 3) == []
