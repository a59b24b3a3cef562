"""``regnf synth --noise``: a request the noise model cannot serve is one line, exit 1, nothing written."""

from __future__ import annotations

from pathlib import Path

import pytest

from regnf.cli import commands_fields
from regnf.cli.app import EXIT_USAGE
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails, run_cli


def _never(*args: object, **kwargs: object) -> None:
    raise AssertionError("the command started its work before checking its inputs")


def test_noise_on_an_object_is_refused_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(commands_fields, "capture_object", _never)
    monkeypatch.setattr(commands_fields, "capture_room", _never)
    before = snapshot(tmp_path)
    line = assert_fails(capsys, ["synth", "--names", "ac-room", "c", "--noise", "sensor",
                                 "--out", str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")],
                        r"^--noise sensor: the noise model applies to rooms .*not to objects \['c'\]$")
    assert "ac-room" in line
    assert changes(before, snapshot(tmp_path)) == []


def test_unknown_noise_level_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(tmp_path)
    with pytest.raises(SystemExit) as exc:  # the option parser's own exit
        run_cli(capsys, ["synth", "--names", "ac-room", "--noise", "loud", "--out", str(tmp_path / "out")])
    assert exc.value.code == EXIT_USAGE
    assert "invalid choice 'loud'" in " ".join(capsys.readouterr().err.split())
    assert changes(before, snapshot(tmp_path)) == []
