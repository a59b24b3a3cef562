"""``regnf train`` warns when one field cannot resolve a capture: the finest cell over its extent."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from regnf.captures.model import Capture
from regnf.cli.capture_plan import CELL_WARN_M, cell_size_warning


def _capture(metres_per_unit: float) -> Capture:
    worldtogt = np.diag([metres_per_unit] * 3 + [1.0])
    box = {"aabb": np.array([[-1.0] * 3, [1.0] * 3]), "near": 0.05, "far": 4.0}
    return Capture(Path("/nowhere/flat"), 4, 3, [], worldtogt, box)


def test_a_room_gets_no_warning_and_an_apartment_gets_its_cell_size() -> None:
    # A 5.1 m room at 256 cells: 2 cm cells.
    assert cell_size_warning(_capture(2.55), 256) is None
    # A 20.4 m apartment: 8.0 cm cells, said with the extent.
    line = cell_size_warning(_capture(10.2), 256)
    assert line is not None and "20.4 m across" in line and "cells of 8.0 cm" in line
    assert line.startswith("/nowhere/flat:")


def test_the_limit_is_the_constant() -> None:
    at_limit = CELL_WARN_M * 256 / 2.0
    assert cell_size_warning(_capture(at_limit), 256) is None
    assert cell_size_warning(_capture(at_limit * 1.01), 256) is not None
