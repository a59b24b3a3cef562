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


def install() -> None:
    """Make tyro's option and command descriptions go through :func:`plain_help` (once)."""
    from tyro import _docstrings

    if getattr(_docstrings, "_regnf_plain_help", False):
        return
    field_docstring, callable_description = _docstrings.get_field_docstring, _docstrings.get_callable_description

    def get_field_docstring(cls: Any, field_name: str, markers: Any) -> str | None:
        text = field_docstring(cls, field_name, markers)
        return None if text is None else plain_help(text, _modules(cls))

    def get_callable_description(f: Any) -> str:
        return plain_help(callable_description(f), _modules(f))

    _docstrings.get_field_docstring = get_field_docstring
    _docstrings.get_callable_description = get_callable_description
    _docstrings._regnf_plain_help = True
