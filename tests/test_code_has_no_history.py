"""The code holds no history: no calendar dates in any module of the package (docstrings and
``--help`` texts come from them); when a thing was measured belongs to the benchmarks page."""

from __future__ import annotations

import re

import pytest

from tests.test_import_layers import FOLDERS

MONTHS = "january|february|march|april|may|june|july|august|september|october|november|december"
DATE = re.compile(
    r"\b(19|20)\d\d[-/.](0?[1-9]|1[0-2])[-/.](0?[1-9]|[12]\d|3[01])\b"  # 2026-12-05
    rf"|\b(0?[1-9]|[12]\d|3[01])(st|nd|rd|th)?\s+({MONTHS})\s+(19|20)\d\d\b"  # 5 December 2026
    rf"|\b({MONTHS})\s+(0?[1-9]|[12]\d|3[01])(st|nd|rd|th)?,?\s+(19|20)\d\d\b",  # December 5, 2026
    re.IGNORECASE,
)


def dates_in(text: str) -> list[tuple[int, str]]:
    """(line, match) of every calendar date in ``text``."""
    return [(text.count("\n", 0, m.start()) + 1, m.group(0)) for m in DATE.finditer(text)]


@pytest.mark.parametrize("text, found", [
    ("a tenth of a pixel (measured 2026-12-05 on two cores)", ["2026-12-05"]),
    ("0.1 until 5 December 2026, then 0.2", ["5 December 2026"]),
    ("as of Dec. nothing; December 7, 2026 it was", ["December 7, 2026"]),
    ("1e-4 of 256 x 192 at 2.0-10.5 m; threads 2026 and 12 views", []),
])
def test_the_pattern_finds_dates_and_only_dates(text: str, found: list[str]) -> None:
    assert [m for _, m in dates_in(text)] == found


def test_no_module_holds_a_date() -> None:
    modules = sorted(p for folder in FOLDERS.values() for p in folder.glob("*.py"))
    assert len(modules) > 100
    dated = [f"{p.relative_to(FOLDERS['cli'].parent)}:{line}: {m}" for p in modules
             for line, m in dates_in(p.read_text(encoding="utf-8"))]
    assert not dated, "dates in the code (move the history to docs/):\n" + "\n".join(dated)
