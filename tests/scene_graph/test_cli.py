"""The stage commands through ``regnf.cli.app.main``: new, add-instance, show, export."""

from __future__ import annotations

import json

import numpy as np

from regnf.cli.app import main
from regnf.scene_graph import read_stage
from tests.cli.cli_helpers import assert_fails

from .helpers import checkpoint, registration_json, similarity


def test_stage_commands(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    scene = checkpoint(src, "room", "scene", scale=3.0)
    c = checkpoint(src, "c", "chair", seed=1)
    wt = checkpoint(src, "wt", "table", symmetry=0, seed=2)
    fc = checkpoint(src, "fc", "chair", seed=3)
    stage = tmp_path / "out" / "room.usda"
    assert main(["stage", "new", str(stage), "--scene", str(scene), "--library", str(c), str(wt),
                 "--proxy-resolution", "12"]) == 0
    M = similarity(0.5, (1.0, -0.5, 0.0), 1.0)
    res = tmp_path / "reg.json"
    res.write_text(json.dumps(registration_json("c", c, M)))
    assert main(["stage", "add-instance", str(stage), "--result", str(res)]) == 0
    # A new library object arrives with its registration; a failed one is refused.
    res2 = tmp_path / "reg2.json"
    res2.write_text(json.dumps(registration_json("fc", fc, similarity(2.0, (0, 1, 0), 1.0), accepted=False,
                                                 confidence=0.2)))
    assert_fails(capsys, ["stage", "add-instance", str(stage), "--result", str(res2)], "not accepted")
    assert main(["stage", "add-instance", str(stage), "--result", str(res2), "--force",
                 "--id", "forced_fc"]) == 0
    capsys.readouterr()
    assert main(["stage", "show", str(stage)]) == 0
    out = capsys.readouterr().out
    assert "chair: c, fc" in out and "table: wt" in out
    assert "c_1: c [chair] at (1.000, -0.500, 0.000) m, heading 28.6 deg, scale 1.0000; regnf, confidence 0.930" in out
    assert "forced_fc" in out and "NOT accepted" in out
    usdz = tmp_path / "pkg" / "room.usdz"
    assert main(["stage", "export", str(stage), "--usdz", str(usdz)]) == 0
    assert usdz.is_file()
    np.testing.assert_allclose(read_stage(usdz).instances["c_1"].object_to_scene, M, atol=1e-12)
    # Proxies came from marching cubes of the fields: in metres, around the field's blob.
    rec = read_stage(stage).library["c"]
    assert len(rec.proxy.points) > 50 and rec.proxy.colors is not None
    assert_fails(capsys, ["stage", "show", str(tmp_path / "missing.usda")], "not a regnf stage|no such stage")
