"""Labels of generated variants: 3D boxes against boxes built by hand, and the format option."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from regnf.cli.app import main
from regnf.datasets.variant_labels import instance_boxes, parse_formats
from regnf.scene_graph import add_instance, read_stage
from tests.scene_graph.helpers import OBJECTS, make_stage, similarity


def test_each_box_is_the_shown_object_s_mesh_box_where_the_instance_stands(tmp_path: Path) -> None:
    stage = make_stage(tmp_path, names=("c", "dc", "t"))
    add_instance(stage, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(stage, "t", similarity(-0.3, (0.3, 2.3, 0.1), 1.5, tilt=0.2))
    scene = read_stage(stage)
    ids = {name: k + 1 for k, name in enumerate(sorted(scene.instances))}
    # The chair instance shows the other chair, as a replacement variant does.
    selections = {name: ("dc" if inst.library_name == "c" else inst.library_name)
                  for name, inst in scene.instances.items()}
    boxes = instance_boxes(scene, selections, ids)
    assert set(boxes) == set(scene.instances)
    for name, box in boxes.items():
        lib = selections[name]
        yaw, t, s, tilt = (0.5, (2.2, -0.5, 0.0), 1.0, 0.0) if lib == "dc" else (-0.3, (0.3, 2.3, 0.1), 1.5, 0.2)
        size = np.asarray(OBJECTS[lib][2])
        # By hand: the proxy box stands on z = 0 about the Z axis; the instance turns it by
        # yaw about Z after tilting it about X, scales by s and moves it by t.
        cz, sz, cx, sx = math.cos(yaw), math.sin(yaw), math.cos(tilt), math.sin(tilt)
        R = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]]) @ np.array([[1.0, 0, 0], [0, cx, -sx], [0, sx, cx]])
        centre = s * R @ np.array([0.0, 0.0, size[2] / 2]) + np.asarray(t)
        assert box["library_name"] == lib and box["class"] == OBJECTS[lib][0] and box["id"] == ids[name]
        np.testing.assert_allclose(box["center"], centre, atol=1e-5)
        np.testing.assert_allclose(box["half_extents"], s * size / 2, atol=1e-5)
        np.testing.assert_allclose(box["rotation"], R, atol=1e-6)


def test_formats_are_parsed_and_unknown_names_refused() -> None:
    assert parse_formats("coco, nerfstudio") == ("nerfstudio", "coco")
    assert parse_formats("coco,coco") == ("coco",)
    with pytest.raises(ValueError, match="unknown data set format yolo"):
        parse_formats("coco,yolo")
    with pytest.raises(ValueError, match="unknown data set format"):
        parse_formats(" , ")


def test_generate_refuses_an_unknown_format_in_one_line_before_any_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    stage = make_stage(tmp_path, names=("c", "t"))
    out = tmp_path / "data"
    assert main(["generate", str(stage), "--out", str(out), "--format", "nerfstudio,voc"]) == 1
    err = capsys.readouterr().err.strip()
    assert "unknown data set format voc" in err and len(err.splitlines()) == 1
    assert not out.exists()
