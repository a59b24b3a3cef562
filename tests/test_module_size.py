"""Small files with one concept each: no module of the package is over 600 lines."""

from __future__ import annotations

from tests.test_import_layers import FOLDERS

MAX_LINES = 600
"""The most lines a module of the package may hold."""


def test_no_module_is_over_the_limit() -> None:
    modules = sorted(p for folder in FOLDERS.values() for p in folder.glob("*.py"))
    assert len(modules) > 100
    sizes = {p: len(p.read_text(encoding="utf-8").splitlines()) for p in modules}
    over = [f"{p.relative_to(FOLDERS['cli'].parent)}: {n} lines" for p, n in sizes.items() if n > MAX_LINES]
    assert not over, f"modules over {MAX_LINES} lines (split them along their concepts):\n" + "\n".join(over)
