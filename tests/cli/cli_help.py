"""What a command's ``--help-all`` must show: every leaf setting of its config, with its docstring."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import textwrap
import typing

import pytest

from regnf.cli.app import main


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the docstring written under it in the source of dataclass ``cls``."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs = {}
    for node, after in itertools.pairwise(body):
        if (isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
            docs[node.target.id] = after.value.value
    return docs


def leaf_settings(cls: type, prefix: str) -> list[tuple[str, str | None]]:
    """(option, docstring) of every leaf field of the nested dataclass ``cls`` that the command
    line offers (not the ones marked ``tyro.conf.Suppress``), each option ``prefix`` + its dotted
    path (``prefix``: ``"--"`` at the top, ``"--registration."`` nested); the docstrings as the
    help shows them (:func:`regnf.cli.help_text.plain_help`)."""
    from tyro.conf import Suppress

    from regnf.cli.help_text import plain_help

    hints = typing.get_type_hints(cls)
    marked = typing.get_type_hints(cls, include_extras=True)
    suppress = typing.get_args(Suppress[int])[1:]
    modules = [c.__module__ for c in cls.__mro__]
    docs = {}
    for c in reversed(cls.__mro__[:-1]):  # a field's docstring from the class that declares it last
        docs |= {k: plain_help(v, modules) for k, v in field_docs(c).items()} if dataclasses.is_dataclass(c) else {}
    out = []
    for f in dataclasses.fields(cls):
        option = f"{prefix}{f.name.replace('_', '-')}"
        if typing.get_origin(marked[f.name]) is typing.Annotated and \
                any(m in suppress for m in typing.get_args(marked[f.name])[1:]):
            continue
        if dataclasses.is_dataclass(hints[f.name]):
            out += leaf_settings(hints[f.name], option + ".")
        else:
            out.append((option, docs.get(f.name)))
    return out


def assert_documented(settings: list[tuple[str, str | None]], help_text: str) -> None:
    """Every option is in ``help_text`` (whitespace collapsed), with its docstring's first words."""
    for option, doc in settings:
        assert option in help_text, option
        if doc:  # the help is the docstring (its first words: the help text wraps the rest)
            assert " ".join(doc.split()[:6]) in help_text, (option, doc)


def help_text(command: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> str:
    """What ``regnf COMMAND --help-all`` prints (wide, box drawing and line wrapping undone)."""
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as done:
        main([command, "--help-all"])
    assert done.value.code == 0
    return " ".join(capsys.readouterr().out.replace("│", " ").split())
