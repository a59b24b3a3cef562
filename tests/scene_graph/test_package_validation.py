"""Packaging (.usda, .usdc, self-contained .usdz) and OpenUSD's validators on our stages."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
from pxr import Sdf, Usd, Vt

from regnf.scene_graph import (
    add_instance,
    export_stage,
    make_replacement_layer,
    read_stage,
    validate_stage,
)
from regnf.scene_graph.embedded_checkpoint import (
    read_embedded_checkpoint,
    write_embedded_checkpoint,
)
from regnf.scene_graph.errors import StageError

from .helpers import make_stage, similarity


@pytest.fixture(scope="module")
def stage_path(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pkg")
    path = make_stage(folder)
    add_instance(path, "c", similarity(0.3, (1, 2, 0), 1.0))
    add_instance(path, "c", similarity(1.3, (-1, 2, 0), 1.0))
    add_instance(path, "t", similarity(-0.4, (0, -1, 0), 1.1))
    return path


def _same_instances(a, b):
    assert {k: v.library_name for k, v in a.instances.items()} == {k: v.library_name for k, v in b.instances.items()}
    for k in a.instances:
        np.testing.assert_array_equal(a.instances[k].object_to_scene, b.instances[k].object_to_scene)
    for k in a.library:
        np.testing.assert_array_equal(a.library[k].proxy.points, b.library[k].proxy.points)


def test_usdz_is_self_contained(stage_path, tmp_path):
    out = export_stage(stage_path, tmp_path / "pkg" / "scene.usdz")
    with zipfile.ZipFile(out) as z:
        names = z.namelist()
        assert names[0] == "scene.usdc"  # the root layer comes first
        assert {"fields/scene_field.usdc", "fields/c.usdc", "library/c.usda",
                "slots/chair.usda", "slots/table.usda"} <= set(names)
        assert not any(n.endswith(".safetensors") for n in names)
        assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())
    # Nothing outside the package is needed.
    stage = Usd.Stage.Open(str(out))
    assert len(stage.GetPrototypes()) == 2
    packaged = read_stage(out)
    _same_instances(read_stage(stage_path), packaged)
    assert "[fields/c.usdc]" in str(packaged.library["c"].checkpoint)
    # The embedded checkpoints are the files, byte for byte.
    for name in ("c", "dc", "t"):
        data = read_embedded_checkpoint(str(packaged.library[name].checkpoint))
        assert data == (stage_path.parent / "fields" / f"{name}.safetensors").read_bytes()
    data = read_embedded_checkpoint(str(packaged.scene.checkpoint))
    assert data == (stage_path.parent / "fields" / "scene_field.safetensors").read_bytes()


def test_embedded_checkpoint_corruption_is_reported(stage_path, tmp_path):
    src = stage_path.parent / "fields" / "c.safetensors"
    layer_path = write_embedded_checkpoint(src, tmp_path / "c.usdc")
    layer = Sdf.Layer.FindOrOpen(str(layer_path))
    attr = layer.GetPrimAtPath("/Checkpoint").attributes["regnf:checkpoint:safetensors"]
    data = np.array(attr.default, dtype=np.uint8)
    data[len(data) // 2] ^= 0xFF
    attr.default = Vt.UCharArray.FromNumpy(data)
    layer.Save()
    with pytest.raises(StageError, match="SHA-256 mismatch") as err:
        read_embedded_checkpoint(str(layer_path))
    assert str(layer_path) in str(err.value)


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_export_usdc_usda(stage_path, tmp_path, suffix):
    out = export_stage(stage_path, tmp_path / f"exp{suffix}")
    if suffix == ".usdc":
        assert out.read_bytes()[:8] == b"PXR-USDC"
    _same_instances(read_stage(stage_path), read_stage(out))


def test_usd_validation_reports_no_errors(stage_path, tmp_path):
    swap = make_replacement_layer(stage_path, {"c_1": "dc"}, stage_path.parent / "swap.usda")
    usdc = export_stage(stage_path, tmp_path / "b.usdc")
    for path in (stage_path, swap, usdc, stage_path.parent / "library" / "c.usda",
                 stage_path.parent / "slots" / "chair.usda"):
        report = validate_stage(path)
        assert len(report.validators) > 10
        assert report.errors == [], (path, report.errors)


def test_usdz_validation_reports_no_errors(stage_path, tmp_path):
    """Checkpoints travel as USD layers, so the package holds only file types the usdz
    specification admits, and every validator passes."""
    report = validate_stage(export_stage(stage_path, tmp_path / "v.usdz"))
    assert len(report.validators) > 10
    assert report.errors == []


def test_a_package_exports_back_to_a_plain_stage(stage_path, tmp_path):
    """Exporting a .usdz to .usda unpacks its checkpoints beside the new stage, byte for byte."""
    usdz = export_stage(stage_path, tmp_path / "pkg" / "scene.usdz")
    plain = export_stage(usdz, tmp_path / "plain" / "scene.usda")
    back = read_stage(plain)
    _same_instances(read_stage(stage_path), back)
    for name in ("c", "dc", "t"):
        assert back.library[name].checkpoint == tmp_path / "plain" / "fields" / f"{name}.safetensors"
        assert back.library[name].checkpoint.read_bytes() == (stage_path.parent / "fields" / f"{name}.safetensors").read_bytes()
    assert (tmp_path / "plain" / "fields" / "scene_field.safetensors").is_file()
