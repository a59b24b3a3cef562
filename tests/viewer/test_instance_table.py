"""The viewer's instance table says how each instance was found (no browser needed)."""

from __future__ import annotations

from pathlib import Path

from regnf.scene_graph import add_instance, add_instance_from_registration, read_stage
from regnf.viewer.edit_panel import instance_table
from tests.scene_graph.helpers import make_stage, registration_json, similarity


def test_the_table_names_discovery_a_box_registration_a_forced_one_and_a_hand_placement(tmp_path: Path) -> None:
    stage = make_stage(tmp_path, ("c", "dc", "t"))
    fields = stage.parent / "fields"
    record = {"found_by": "discovery", "candidate": 0, "chosen": "dc",
              "tried": [{"library": "dc", "screened": 0.6, "confidence": 0.83, "accepted": True}]}
    add_instance_from_registration(
        stage, {**registration_json("dc", fields / "dc.safetensors", similarity(1.0, (0, 1, 0), 1.0)),
                "discovery": record}, instance_id="dc_1")
    add_instance_from_registration(
        stage, registration_json("c", fields / "c.safetensors", similarity(0.2, (1, 0, 0), 1.0)), instance_id="c_1")
    add_instance_from_registration(
        stage, registration_json("c", fields / "c.safetensors", similarity(0.4, (2, 0, 0), 1.0), accepted=False,
                                 confidence=0.3), force=True, instance_id="c_2")
    add_instance(stage, "t", similarity(0.0, (0, -1, 0), 1.0), instance_id="t_1")
    rows = {line.split("|")[1].strip(): line for line in instance_table(read_stage(stage)).splitlines()[2:]}
    assert set(rows) == {"dc_1", "c_1", "c_2", "t_1"}
    assert rows["dc_1"].endswith("| discovery |")
    assert rows["c_1"].endswith("| regnf |")
    assert rows["c_2"].endswith("| 0.300 | regnf, forced |")
    assert "| - | placed by hand |" in rows["t_1"]
