"""``regnf register``: a matching object is registered and saved; a chair against a table's
box is reported as a failed registration (exit code 3), and nothing reaches the stage.

Checkpoint loading is replaced by exact analytic fields (the registration itself runs for
real), so the test needs no trained field.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import regnf.cli.commands_registration as commands
from regnf.cli.app import main
from regnf.fields.analytic import Box, Cylinder, Union
from regnf.registration.pipeline import RegistrationConfig
from tests.adversarial.disk import changes, snapshot
from tests.registration.fixtures import make_object, make_scene, placement
from tests.scene_graph.helpers import make_stage

from .cli_help import assert_documented, help_text, leaf_settings


def _table():
    """A table-like object: a top on one pillar, base on z = 0 (field frame = metres)."""
    return Union(Box(half_extents=(0.4, 0.4, 0.03), center=(0.0, 0.0, 0.72)),
                 Cylinder(radius=0.06, half_height=0.35, center=(0.0, 0.0, 0.35)),
                 label="table", name="table")


def _printed(capsys: pytest.CaptureFixture[str]) -> str:
    """Everything the command printed (the console writes to stderr), line wrapping undone."""
    cap = capsys.readouterr()
    return " ".join((cap.out + cap.err).split())


@pytest.fixture()
def fields(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, Path]:
    """Paths the command is given, and the analytic field each one loads as."""
    chair_to_scene = placement([0, 0, 1], 0.7, [1.0, -0.5, 0.0], 1.0)
    chair_scene = make_scene(chair_to_scene)
    table_scene = Union(Box(half_extents=(3.0, 3.0, 0.05), center=(0.0, 0.0, -0.05)), _table(),
                        label="scene", name="room")
    table = {str(tmp_path / "table_room.safetensors"): table_scene,
             str(tmp_path / "chair_room.safetensors"): chair_scene,
             str(tmp_path / "chair.safetensors"): make_object()}
    monkeypatch.setattr(commands, "load_field", lambda path, device="cpu": table[str(path)])
    (tmp_path / "table_box.json").write_text(json.dumps({"center": [0, 0, 0.375], "size": [0.8, 0.8, 0.75]}))
    corners = [(chair_to_scene @ np.array([x, y, z, 1.0]))[:3].tolist()
               for x in (-0.4, 0.4) for y in (-0.25, 0.25) for z in (0.0, 0.75)]
    (tmp_path / "chair_box.json").write_text(json.dumps({"corners": corners}))
    return {name: tmp_path / f"{name}.{ext}" for name, ext in (
        ("table_room", "safetensors"), ("chair_room", "safetensors"), ("chair", "safetensors"),
        ("table_box", "json"), ("chair_box", "json"))}


def test_register_a_matching_object_succeeds(fields, tmp_path, capsys) -> None:
    out = tmp_path / "ok.json"
    assert main(["register", "--scene", str(fields["chair_room"]), "--library", str(fields["chair"]),
                 "--box", str(fields["chair_box"]), "--out", str(out)]) == 0
    assert "registered" in _printed(capsys)
    saved = json.loads(out.read_text())
    assert saved["accepted"] is True
    # The saved object -> scene transform is the placement (fields in metres: frames coincide).
    M = np.asarray(saved["object_to_scene_metres"])
    np.testing.assert_allclose(M, placement([0, 0, 1], 0.7, [1.0, -0.5, 0.0], 1.0), atol=5e-3)


def test_chair_against_a_table_box_is_reported_as_failed(fields, tmp_path, capsys) -> None:
    out = tmp_path / "bad.json"
    stage = make_stage(tmp_path / "stage", ("c", "t"))
    before = snapshot(stage.parent)
    assert main(["register", "--scene", str(fields["table_room"]), "--library", str(fields["chair"]),
                 "--box", str(fields["table_box"]), "--out", str(out), "--stage", str(stage)]) == 3
    text = _printed(capsys)
    assert "registration FAILED" in text and "below the acceptance threshold" in text
    assert "nothing written" in text
    assert changes(before, snapshot(stage.parent)) == []
    saved = json.loads(out.read_text())  # the result is still saved, flagged
    assert saved["accepted"] is False
    assert saved["confidence"] < RegistrationConfig().acceptance_threshold


def test_help_lists_every_registration_setting_with_its_documentation(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    text = help_text("register", capsys, monkeypatch)
    settings = leaf_settings(RegistrationConfig, "--registration.")
    assert len(settings) > 60  # sampling x 2, trace x 2, initialisation, refinement, the rest
    assert_documented(settings, text)


def test_a_nested_registration_setting_reaches_the_registration(
        fields: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen = {}

    def spy(scene, library, proposal, config):
        seen["config"] = config
        raise SystemExit(0)

    monkeypatch.setattr("regnf.registration.pipeline.register", spy)
    main(["register", "--scene", str(fields["chair_room"]), "--library", str(fields["chair"]),
          "--box", str(fields["chair_box"]), "--out", str(tmp_path / "r.json"),
          "--registration.init.top-k", "1", "--registration.refine.optimizer", "adam",
          "--registration.no-upright", "--registration.refine.max-offset", "0.002"])
    cfg = seen["config"]
    assert (cfg.init.top_k, cfg.refine.optimizer, cfg.upright, cfg.refine.max_offset) == (1, "adam", False, 0.002)
