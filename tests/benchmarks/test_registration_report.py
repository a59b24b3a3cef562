"""The registration benchmark's wrong-object pairs and the rates reported from its rows."""

from __future__ import annotations

from regnf.benchmarks.registration import wrong_pairs
from regnf.benchmarks.registration_report import coverage_table, wrong_pair_rates
from regnf.registration.metrics import within_bars
from regnf.synthetic.library import LIBRARY_NAMES


def test_wrong_pairs_cross_classes_and_pair_every_chair_with_every_other_chairs_box() -> None:
    tables = {"et", "t", "wt"}
    chairs = set(LIBRARY_NAMES) - tables
    atbl = wrong_pairs("atbl-room")  # three tables: every chair into each; no table into a table
    assert sorted(atbl) == sorted((c, box) for box in ("et", "t", "wt") for c in chairs)
    ac = wrong_pairs("ac-room")  # five chairs: every table and every other chair into each
    assert sorted(ac) == sorted((o, box) for box in chairs for o in LIBRARY_NAMES if o != box)
    assert all(o != box for o, box in wrong_pairs("mix-room"))


def _row(obj: str, box: str, conf: float, accepted: bool, difference: float | None = None,
         **errors: float) -> dict:
    return {"scene": "ac-room", "object": obj, "box_object": box, "method": "regnf", "views": "multi",
            "coverage": "low", "library_source": "mesh", "wrong_pair": obj != box, "confidence": conf,
            "accepted": accepted, "seconds": 1.0, "difference_observed": difference,
            "rot_geodesic_sym_rad": None, "trans_rel_diag_sym": None, "scale_rel": None, **errors}


def test_rates_count_false_accepts_and_wrong_chairs_scoring_below_the_right_one() -> None:
    good = {"rot_geodesic_sym_rad": 0.01, "trans_rel_diag_sym": 0.005, "scale_rel": 0.002}
    rows = [
        _row("dc", "dc", 0.8, True, **good),
        _row("c", "dc", 0.7, True, 0.9),    # accepted, but below the right chair: identified
        _row("mc", "dc", 0.9, True, 0.8),   # above the right chair: not identified
        _row("fc", "dc", 0.95, False, 0.9),  # rejected: identified
        _row("fc-nop", "dc", 0.85, True, 0.01),  # above it, but its difference was never observed
        _row("t", "dc", 0.65, True, 0.7),   # a table accepted in a chair's box: a false accept
        _row("wt", "dc", 0.3, False, 0.7),
    ]
    (rates,) = wrong_pair_rates(rows)
    unidentified = rates.pop("within_unidentified")
    assert rates == {"coverage": "low", "library_source": "mesh", "cross_pairs": 2, "cross_accepted": 1,
                     "within_pairs": 4, "within_accepted": 3, "within_rejected_or_lower": 2,
                     "within_unidentified_unobserved": 1}
    assert [u.split(" (")[0] for u in unidentified] == ["ac-room: mc in dc's box", "ac-room: fc-nop in dc's box"]
    assert within_bars(rows[0]) and not within_bars({**rows[0], "scale_rel": 0.011})
    assert "| low | mesh | 1 | 1 | 1 | 1 |" in coverage_table(rows)
