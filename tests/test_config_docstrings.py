"""Every setting of a library config says in one line what it is: the why goes to docs/decisions."""

from __future__ import annotations

import ast
from pathlib import Path

LIBRARY = Path(__file__).resolve().parents[1] / "src" / "regnf"
COMMANDS = ("cli", "benchmarks")
"""Packages whose dataclasses are commands: an option's help may describe what the command does."""


def is_dataclass(node: ast.ClassDef) -> bool:
    names = [d.func if isinstance(d, ast.Call) else d for d in node.decorator_list]
    return any(isinstance(n, ast.Name) and n.id == "dataclass" for n in names)


def multi_line_field_docstrings(path: Path) -> list[str]:
    """``Class.field`` for each dataclass field in ``path`` whose docstring spans several lines."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not (isinstance(node, ast.ClassDef) and is_dataclass(node)):
            continue
        for field, doc in zip(node.body, node.body[1:]):
            if (isinstance(field, ast.AnnAssign) and isinstance(doc, ast.Expr)
                    and isinstance(doc.value, ast.Constant) and isinstance(doc.value.value, str)
                    and "\n" in doc.value.value.strip()):
                found.append(f"{node.name}.{ast.unparse(field.target)}")
    return found


def test_library_config_fields_have_one_line_docstrings() -> None:
    offenders = {
        str(path.relative_to(LIBRARY)): names
        for path in sorted(LIBRARY.rglob("*.py"))
        if path.relative_to(LIBRARY).parts[0] not in COMMANDS
        and (names := multi_line_field_docstrings(path))
    }
    assert offenders == {}


def test_the_check_finds_a_multi_line_docstring(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text('from dataclasses import dataclass\n\n@dataclass\nclass C:\n    a: int = 1\n    """One line."""\n'
                      '    b: int = 2\n    """Two\n    lines."""\n')
    assert multi_line_field_docstrings(sample) == ["C.b"]
