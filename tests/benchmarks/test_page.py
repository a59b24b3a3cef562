"""``regnf bench page``: the results page from JSON files written here, not by the benchmarks."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from regnf.benchmarks.page import SECTIONS, results_page
from regnf.cli.app import main

META = {"command": "regnf bench registration --json r.json --coverage low --library mesh",
        "date": "2030-01-02 03:04:05", "device": "cpu", "torch": "9.9", "threads": 2, "cpu": "x86_64"}


def _row(obj: str, rot: float, accepted: bool) -> dict:
    return {"scene": "ac-room", "object": obj, "method": "regnf", "views": "multi", "wrong_pair": False,
            "coverage": "low", "library_source": "mesh", "accepted": accepted, "rot_geodesic_sym_rad": rot,
            "trans_rel_diag_sym": 0.001, "scale_rel": 0.002, "seconds": 2.0}


def test_the_page_shows_what_the_json_holds_and_names_the_command_for_the_rest(tmp_path: Path) -> None:
    # Three pairs: one accepted within the bars, one accepted outside them (0.03 rad > 0.02), one
    # rejected within them.
    rows = [_row("c", 0.001, True), _row("dc", 0.03, True), _row("fc", 0.005, False)]
    (tmp_path / "registration.json").write_text(json.dumps({"meta": META, "rows": rows}))
    page = results_page(tmp_path)
    assert page.count("Machine: x86_64, 2 torch threads, torch 9.9, device cpu. Runs: 2030-01-02.") == 1
    assert f"`{META['command']}`, 2030-01-02." in page
    # coverage | library | pairs | accepted | within bars | accepted and within | median ΔR ...
    assert "| low | mesh | 3 | 2 | 2 | 1 | 0.0050 | 0.10 | 0.20 | 2.0 | 2.0 |" in page
    for s in SECTIONS:
        assert f"## {s.title}" in page
        if s.name != "registration":
            assert f"--json {tmp_path.as_posix()}/{s.name}.json`" in page


def test_the_command_writes_the_page_and_refuses_a_broken_result_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "benchmarks.md"
    (tmp_path / "res").mkdir()
    assert main(["bench", "page", "--results", str(tmp_path / "res"), "--out", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == results_page(tmp_path / "res")
    capsys.readouterr()
    (tmp_path / "res" / "discover.json").write_text("{not json")
    assert main(["bench", "page", "--results", str(tmp_path / "res"), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "discover.json: not a readable benchmark result" in err


def test_the_discovery_section_links_its_pictures_relative_to_the_page(tmp_path: Path) -> None:
    res = tmp_path / "docs" / "results"
    (res / "discover_png").mkdir(parents=True)
    (res / "discover_png" / "ac-room_low.png").write_bytes(b"\x89PNG")
    row = {"scene": "ac-room", "left_out": {}, "coverage": "low", "true_instances": 5, "candidates": 6,
           "found": 5, "identified": 5, "within_bars": 5, "false_instances": 0, "unmatched_candidates": 1,
           "seconds": 29.4, "instances": [], "false": []}
    (res / "discover.json").write_text(json.dumps({"meta": {**META, "command": "regnf bench discover"},
                                                   "rows": [row]}))
    page = results_page(res, tmp_path / "docs")
    assert "| ac-room | all 8 | low | 5 | 6 | 5 | 5 | 5 | 0 | 1 | 29 |" in page
    assert "Pictures: [ac-room_low](results/discover_png/ac-room_low.png)." in page
