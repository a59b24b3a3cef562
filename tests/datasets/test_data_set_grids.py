"""The grids of a stage kept in a cache folder (``regnf demo``): baked once, read back the same,
baked again when damaged, incomplete or made for other cameras."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest
import torch

from regnf.compositor.cameras_io import OrbitConfig, field_bounds_metres, orbit_around_bounds
from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.file_lock import folder_lock
from regnf.datasets.data_set_grids import (
    INDEX,
    bake_for_data_set,
    cached_stage_grids,
    load_data_set_grids,
    stage_grids_key,
)
from regnf.render.baked_field import BakeConfig
from regnf.scene_graph import add_instance
from tests.scene_graph.helpers import make_stage, similarity

SUBSTITUTE = StageCompositeConfig(mode="substitute")


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = make_stage(tmp_path_factory.mktemp("grids"), names=("c", "dc"))
    add_instance(path, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    return path


def cameras(stage: Path, n: int = 2, width: int = 24) -> list:
    scene = composite_from_stage(stage, StageCompositeConfig(mode="scene")).field.scene
    return orbit_around_bounds(field_bounds_metres(scene), OrbitConfig(n=n, width=width, height=18, radius=4.5))


def same_bits(a, b) -> bool:
    fields = [(a.scene, b.scene), *((a.objects[n], b.objects[n]) for n in a.objects)]
    return sorted(a.objects) == sorted(b.objects) and all(
        torch.equal(x.sdf_grid, y.sdf_grid) and torch.equal(x.rgb_grid, y.rgb_grid) for x, y in fields)


def test_the_grids_are_baked_once_then_read_back(stage: Path, tmp_path: Path) -> None:
    cams = cameras(stage)
    first, seconds = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    assert seconds > 0
    # Both library objects: the instance shows its own (the substitution) or the other chair.
    assert sorted(first.objects) == ["c", "dc"]
    again, seconds = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    assert seconds == 0.0 and same_bits(first, again)
    assert [p.name for p in tmp_path.iterdir()] == ["room"]
    key = json.loads((tmp_path / "room" / INDEX).read_text())["config_key"]
    assert key == stage_grids_key(stage, cams, BakeConfig(), SUBSTITUTE)


def test_a_data_set_s_grids_lack_the_instance_s_own_object(stage: Path, tmp_path: Path) -> None:
    """What a replacement never shows is not baked for a data set; the stage's grids have it,
    with the same bits of the masked scene and the other chair."""
    cams = cameras(stage)
    grids, _ = cached_stage_grids(tmp_path / "cache", "room", stage, cams, BakeConfig(), SUBSTITUTE)
    bake_for_data_set(stage, tmp_path / "data", "key", cams, BakeConfig(), SUBSTITUTE)
    data = load_data_set_grids(tmp_path / "data" / INDEX)
    assert sorted(data.objects) == ["dc"]
    assert torch.equal(data.scene.sdf_grid, grids.scene.sdf_grid)
    assert torch.equal(data.objects["dc"].rgb_grid, grids.objects["dc"].rgb_grid)


def test_other_cameras_or_settings_bake_again_in_the_same_folder(stage: Path, tmp_path: Path) -> None:
    cams = cameras(stage)
    keys = {stage_grids_key(stage, c, b, m) for c, b, m in (
        (cams, BakeConfig(), SUBSTITUTE), (cameras(stage, n=3), BakeConfig(), SUBSTITUTE),
        (cameras(stage, width=32), BakeConfig(), SUBSTITUTE), (cams, BakeConfig(cell_pixels=1.0), SUBSTITUTE),
        (cams, BakeConfig(), StageCompositeConfig(mode="substitute", box_pad=0.5)))}
    assert len(keys) == 5
    # The mode is always substitute: the key does not depend on the one given.
    assert stage_grids_key(stage, cams, BakeConfig(), StageCompositeConfig(mode="scene")) in keys
    # Grids for other cameras replace the ones there, in the one folder of the label.
    first, _ = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    other, seconds = cached_stage_grids(tmp_path, "room", stage, cameras(stage, width=32), BakeConfig(), SUBSTITUTE)
    assert seconds > 0 and other.scene.sdf_grid.shape != first.scene.sdf_grid.shape
    assert [p.name for p in tmp_path.iterdir()] == ["room"]
    back, seconds = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    assert seconds > 0 and same_bits(first, back)


def test_a_damaged_or_incomplete_folder_is_baked_again_to_the_same_bits(stage: Path, tmp_path: Path) -> None:
    cams = cameras(stage)
    first, _ = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    folder = next(tmp_path.iterdir())
    damaged = folder / "scene.safetensors"
    data = bytearray(damaged.read_bytes())
    data[-5] ^= 0xFF
    damaged.write_bytes(bytes(data))
    again, seconds = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    assert seconds > 0 and same_bits(first, again)
    # Grids of the same key without the instance's own object (as a data set keeps them): baked again.
    key = json.loads((folder / INDEX).read_text())["config_key"]
    bake_for_data_set(stage, folder, "another key", cams, BakeConfig(), SUBSTITUTE)
    assert sorted(json.loads((folder / INDEX).read_text())["objects"]) == ["dc"]
    (folder / INDEX).write_text((folder / INDEX).read_text().replace("another key", key))
    third, seconds = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    assert seconds > 0 and same_bits(first, third)


def test_a_second_caller_waits_for_the_one_baking_and_says_so(stage: Path, tmp_path: Path) -> None:
    """Another holder of the folder's lock (a thread here, as another process would): the call
    says it waits, then reads the grids once the holder is done."""
    cams = cameras(stage)
    first, _ = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE)
    folder = next(tmp_path.iterdir())
    held, release = threading.Event(), threading.Event()

    def hold() -> None:
        with folder_lock(folder):
            held.set()
            release.wait(10)

    holder = threading.Thread(target=hold)
    holder.start()
    held.wait(10)
    told: list[str] = []
    threading.Timer(0.3, release.set).start()
    again, seconds = cached_stage_grids(tmp_path, "room", stage, cams, BakeConfig(), SUBSTITUTE, on_wait=told.append)
    holder.join()
    assert seconds == 0.0 and same_bits(first, again)
    assert len(told) == 1 and str(folder) in told[0] and "waiting" in told[0]
