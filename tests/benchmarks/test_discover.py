"""The discovery benchmark's scoring: one-to-one box matching by IoU, and the table's notes."""

from __future__ import annotations

import numpy as np

from regnf.benchmarks.discover import markdown_table
from regnf.fields.oriented_box import OrientedBox
from regnf.synthetic.ground_truth import match_boxes


def _box(x: float, size: float = 1.0) -> OrientedBox:
    return OrientedBox(np.array([x, 0.0, 0.5]), np.full(3, size / 2), np.eye(3))


def test_each_box_matches_once_by_the_highest_iou() -> None:
    truth = [_box(0.0), _box(3.0), _box(6.0)]
    # Found: one a little off the first truth, one exactly on the third, one overlapping the
    # second a little (IoU < 0.5), and a stray one.
    found = [_box(0.2), _box(6.0), _box(2.2), _box(10.0)]
    matched, iou = match_boxes(truth, found)
    assert matched == {0: 0, 2: 1}  # truth 1 overlaps nothing by >= 0.5: not found
    np.testing.assert_allclose(iou[0][0], 0.8 / 1.2, atol=0.03)  # x overlap 0.8 of 1
    np.testing.assert_allclose(iou[1][2], 0.2 / 1.8, atol=0.03)
    assert iou[2][1] > 0.99 and iou[1][3] == 0.0
    # Both found boxes cover truth 0; the better one (IoU 1) wins it and the other stays free.
    matched, _ = match_boxes([_box(0.0)], [_box(0.2), _box(0.0)], min_iou=0.3)
    assert matched == {0: 1}


def test_the_table_explains_every_miss() -> None:
    row = {"scene": "r", "coverage": "low", "true_instances": 3, "candidates": 4, "found": 2, "identified": 1,
           "within_bars": 0, "false_instances": 1, "unmatched_candidates": 1, "seconds": 61.0,
           "left_out": {"mc": "unmatched"},
           "instances": [
               {"object": "a", "candidate": None, "iou": 0.31, "within_bars": False, "identified": False},
               {"object": "b", "candidate": 0, "iou": 0.8, "within_bars": False, "identified": False,
                "chosen": None, "confidence": None, "right_object_screened_rank": 1,
                "right_object_confidence": 0.55},
               {"object": "c", "candidate": 1, "iou": 0.9, "within_bars": False, "identified": True,
                "rot_geodesic_rad": 0.004, "trans_rel_diag": 0.0159, "scale_rel": 0.0102},
               {"object": "fc", "candidate": 2, "iou": 0.92, "within_bars": False, "identified": False,
                "chosen": None, "ambiguous": ["fc-nop", "fc"]}],
           "false": [{"candidate": 3, "chosen": "t", "matches": None}]}
    text = markdown_table([row])
    assert "| r | without mc | low | 3 | 4 | 2 | 1 | 0 | 1 | 1 | 61 |" in text
    assert "`a`: not found (best box IoU 0.31)" in text
    assert "`b`: box IoU 0.80, chosen unmatched; the right object ranked 2 by the short registration, confidence 0.550" in text
    assert "`c`: identified, outside the bars (ΔR 0.0040 rad, Δt 1.59 %, Δs 1.02 %)" in text
    assert "`mc` left out of the library: its candidate became unmatched" in text
    assert "false instance `t` in candidate 3" in text
    assert "`fc`: box IoU 0.92, left unmatched: `fc-nop` and `fc` both fit, and they differ only where no view" in text
