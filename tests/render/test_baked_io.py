"""Baked grids on disk: what is saved loads back the same, and a damaged file is refused by name."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from regnf.fields.analytic import Sphere
from regnf.fields.field import FieldInfo, Symmetry
from regnf.render.baked_field import bake
from regnf.render.baked_io import HEADER_KEY, BakedFileError, load_baked, save_baked


@pytest.fixture(scope="module")
def grid():
    ball = Sphere(0.4, (0.1, 0.0, 0.0), color=(0.8, 0.3, 0.2), name="ball")
    ball.info = FieldInfo("chair", "ball", Symmetry(4), {"source": "analytic"})
    return bake(ball, 0.05)


def test_a_saved_grid_loads_back_the_same(grid, tmp_path: Path) -> None:
    back = load_baked(save_baked(grid, tmp_path / "g.safetensors"))
    assert torch.equal(back.sdf_grid, grid.sdf_grid) and torch.equal(back.rgb_grid, grid.rgb_grid)
    assert torch.equal(back.bounds, grid.bounds) and torch.equal(back.to_world, grid.to_world)
    assert (back.info.label, back.info.name, back.info.symmetry.order) == ("chair", "ball", 4)
    assert back.info.provenance["baked"] == json.loads(json.dumps(grid.info.provenance["baked"]))
    x = torch.rand(200, 3) * 1.6 - 0.8
    assert torch.equal(back.sdf(x), grid.sdf(x)) and torch.equal(back.color(x), grid.color(x))
    assert [p.name for p in tmp_path.iterdir()] == ["g.safetensors"]  # no temporary left


def _rewrite(path: Path, tensors: dict, header: dict | None) -> None:
    save_file(tensors, str(path), metadata=None if header is None else {HEADER_KEY: json.dumps(header)})


def test_damaged_files_are_refused_with_the_file_named(grid, tmp_path: Path) -> None:
    good = save_baked(grid, tmp_path / "good.safetensors")
    with open(good, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        header = json.loads(json.loads(f.read(n))["__metadata__"][HEADER_KEY])
    sdf, rgb = grid.sdf_grid[0, 0].contiguous(), grid.rgb_grid[0].contiguous()
    cases = {
        "garbage": None,
        "no_header": ({"sdf": sdf, "rgb": rgb}, None),
        "version": ({"sdf": sdf, "rgb": rgb}, {**header, "version": 99}),
        "shape": ({"sdf": sdf, "rgb": rgb[:, :-1].contiguous()}, header),
        "extra": ({"sdf": sdf, "rgb": rgb, "x": sdf.clone()}, header),
        "bounds": ({"sdf": sdf, "rgb": rgb}, {**header, "bounds": [[0, 0, 0], [0, 1, 1]]}),
        "to_world": ({"sdf": sdf, "rgb": rgb}, {**header, "to_world": [[1, 0, 0], [0, 1, 0]]}),
        "nan": ({"sdf": torch.where(sdf > 0.1, torch.nan, sdf), "rgb": rgb}, header),
    }
    messages = {
        "garbage": "cannot read", "no_header": "not a regnf baked-grid file", "version": "version 99",
        "shape": "'rgb' must be", "extra": "expected the tensors", "bounds": "lo < hi",
        "to_world": "'to_world' must be", "nan": "non-finite",
    }
    for name, case in cases.items():
        path = tmp_path / f"{name}.safetensors"
        if case is None:
            path.write_bytes(np.random.default_rng(0).bytes(256))
        else:
            _rewrite(path, *case)
        with pytest.raises(BakedFileError) as info:
            load_baked(path)
        assert str(info.value).startswith(str(path)) and messages[name] in str(info.value), name
        assert "\n" not in str(info.value)
    with pytest.raises(BakedFileError, match="missing.safetensors"):
        load_baked(tmp_path / "missing.safetensors")
    with pytest.raises(BakedFileError, match=r"\.safetensors files"):
        save_baked(grid, tmp_path / "grid.bin")


def test_loaded_grids_sit_in_aligned_memory_whatever_the_header_length(grid, tmp_path: Path) -> None:
    for pad in range(8):
        grid.info.provenance = {**grid.info.provenance, "note": "x" * pad}
        back = load_baked(save_baked(grid, tmp_path / f"g{pad}.safetensors"))
        assert back.sdf_grid.data_ptr() % 64 == 0 and back.rgb_grid.data_ptr() % 64 == 0, pad
        assert torch.equal(back.sdf_grid, grid.sdf_grid)
