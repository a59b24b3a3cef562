"""Help text of the command line without Sphinx markup.

The options' help is the docstring under each config field, written for the API reference
with Sphinx roles (``:data:`MAX_VIEWS```, ``:func:`~regnf.x.render```). On the command line a
role becomes what it names: a constant's value, a module's path, a function's or attribute's
name. :func:`install` makes tyro read the docstrings through :func:`plain_help`.
"""

from __future__ import annotations

import importlib
import re
import sys
from collections.abc import Sequence
from typing import Any

ROLE = re.compile(r":(?:py:)?(\w+):`~?([^`]+)`")
"""A Sphinx role and its target, e.g. ``:data:`regnf.x.MAX``` or ``:func:`~regnf.x.f```."""


def _constant(target: str, modules: Sequence[str]) -> Any:
    """The value ``target`` (``NAME`` in one of ``modules``, or ``package.module.NAME``) names, or None."""
    path, _, name = target.rpartition(".")
    if path:
        try:
            return getattr(importlib.import_module(path), name, None)
        except ImportError:
            return None
    owners = (sys.modules.get(m) for m in modules)
    return next((getattr(o, name) for o in owners if o is not None and hasattr(o, name)), None)


def _modules(owner: Any) -> list[str]:
    """The modules of a class and its bases (a docstring may come from a base), or a callable's."""
    return [c.__module__ for c in getattr(owner, "__mro__", (owner,)) if hasattr(c, "__module__")]


def plain_help(text: str, modules: Sequence[str] = ()) -> str:
    """``text`` with each Sphinx role replaced by what it names.

    Parameters
    ----------
    text : str
        A docstring.
    modules : sequence of str
        The modules the docstring may belong to: where a bare constant's name is looked up.
    """

    def plain(match: re.Match[str]) -> str:
        role, target = match.group(1), match.group(2)
        if role == "data":
            value = _constant(target, modules)
            if isinstance(value, int) and not isinstance(value, bool):
                return f"{value:,}"
            if isinstance(value, float):
                return f"{value:g}"
        if role == "mod":
            return target
        return target.rpartition(".")[2]

    return ROLE.sub(plain, text)


def unwrapped(text: str) -> str:
    """``text`` with the line breaks of a wrapped docstring joined (a blank line still parts paragraphs),
    so that the terminal wraps the help at its own width."""
    return "\n\n".join(" ".join(paragraph.split()) for paragraph in re.split(r"\n\s*\n", text.strip()))


def install() -> None:
    """Make tyro's option and command descriptions go through :func:`plain_help` (once)."""
    from tyro import _docstrings

    if getattr(_docstrings, "_regnf_plain_help", False):
        return
    field_docstring, callable_description = _docstrings.get_field_docstring, _docstrings.get_callable_description

    def get_field_docstring(cls: Any, field_name: str, markers: Any) -> str | None:
        text = field_docstring(cls, field_name, markers)
        return None if text is None else unwrapped(plain_help(text, _modules(cls)))

    def get_callable_description(f: Any) -> str:
        return plain_help(callable_description(f), _modules(f))

    _docstrings.get_field_docstring = get_field_docstring
    _docstrings.get_callable_description = get_callable_description
    _docstrings._regnf_plain_help = True


BOX_TOP, BOX_BOTTOM, BOX_SIDE, BOX_RULE = "╭─ ", "╰", "│", "│ ─"
"""How tyro draws the boxes of a help text: a titled top border, a bottom border, the sides and
the rule between a group's description and its options."""


def compact_help(text: str, command: str) -> str:
    """The help of ``command`` with only its own options: each group of settings (a nested config,
    ``--registration.*``) shown by its description and the number of its options.

    Parameters
    ----------
    text : str
        The full help tyro renders for the command (``--help-all``).
    command : str
        The command's name (``register``), for the pointer to the full help.
    """
    out: list[str] = []
    boxes: list[tuple[str, list[str]]] = []  # (group path, lines) of each box, in order
    for line in text.splitlines():
        if line.startswith(BOX_TOP):
            title = line[len(BOX_TOP):].rstrip("─╮ ")
            group = title.removesuffix(" options") if title.endswith(" options") else ""
            boxes.append((group, [line]))
            out.append(f"\0{len(boxes) - 1}")  # where the box goes
        elif boxes and boxes[-1][1][-1].startswith((BOX_TOP, BOX_SIDE)):
            boxes[-1][1].append(line)
        else:
            out.append(line)
    shown: list[str] = []
    summed = False
    for line in out:
        if not line.startswith("\0"):
            shown.append(line)
            continue
        group, lines = boxes[int(line[1:])]
        if not group:  # the command's own options and positional arguments
            shown += lines
        elif "." not in group:  # a group of settings: its description and its size
            summed = True
            count = sum(_options(ls) for g, ls in boxes if g == group or g.startswith(f"{group}."))
            head = f"{BOX_TOP}{group} options ({count}, listed by --help-all) "
            width = len(lines[0])
            shown.append(head + "─" * max(1, width - len(head) - 1) + "╮")
            body = lines[1:-1]
            rule = next((i for i, x in enumerate(body) if x.startswith(BOX_RULE)), 0)
            shown += [*body[:rule], lines[-1]]
    if summed:
        shown.append(f"Every setting of every group: regnf {command} --help-all")
    return "\n".join(shown) + "\n"


def _options(lines: list[str]) -> int:
    """The options a box of tyro's help lists: lines that start one, less the second half of a
    flag pair (``--x,`` / ``--no-x``) wrapped onto its own line."""
    starts = [i for i, x in enumerate(lines) if x.startswith(f"{BOX_SIDE} -")]
    return sum(1 for i in starts if not lines[i - 1].rstrip("│ ").endswith(","))
