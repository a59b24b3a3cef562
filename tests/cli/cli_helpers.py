"""Run the ``regnf`` command in-process and check how it fails."""

from __future__ import annotations

import re
from collections.abc import Sequence

import pytest

from regnf.cli.app import EXIT_BAD_INPUT, main


def run_cli(capsys: pytest.CaptureFixture[str], args: Sequence[str]) -> tuple[int, str]:
    """Exit status and stderr of ``regnf ARGS``."""
    capsys.readouterr()  # drop what earlier steps printed
    status = main(list(args))
    return status, capsys.readouterr().err


def assert_fails(capsys: pytest.CaptureFixture[str], args: Sequence[str], pattern: str,
                 status: int = EXIT_BAD_INPUT) -> str:
    """``regnf ARGS`` exits with ``status`` and ends with one error line matching ``pattern``; no traceback.

    Returns the error line.
    """
    code, err = run_cli(capsys, args)
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == status, f"exit status {code}, expected {status}; stderr:\n{err}"
    assert lines, "nothing printed on stderr"
    assert re.search(pattern, lines[-1]), f"{lines[-1]!r} does not match {pattern!r}"
    return lines[-1]
