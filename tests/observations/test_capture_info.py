"""The label a field trained on a capture records: from the capture's own block, else the preset."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regnf.captures.model import Capture
from regnf.synthetic.cache import capture_info


def _capture(meta: dict) -> Capture:
    return Capture(root=Path("/nowhere/kitchen"), width=4, height=3, frames=[], worldtogt=np.eye(4),
                   scene_box={}, meta=meta)


def test_a_users_capture_is_labelled_by_what_the_preset_trains() -> None:
    assert capture_info(_capture({}), room=True).label == "scene"
    assert capture_info(_capture({}), room=False).label == "object"
    assert capture_info(_capture({}), room=False).name == "kitchen"


def test_the_captures_own_block_wins_over_the_preset() -> None:
    chair = {"kind": "object", "label": "chair", "name": "c"}
    assert capture_info(_capture(chair), room=True).label == "chair"
    assert capture_info(_capture({"kind": "scene"}), room=False).label == "scene"
