"""Test options shared by every test module.

``--device``: the torch device of the tests marked ``cuda`` (default ``cpu``). ``make gpu-check``
runs ``pytest -m cuda --device cuda``; CI runs the same tests on the CPU, so the code a GPU takes
cannot rot.
"""

from __future__ import annotations

import pytest

from regnf.core.preflight import PreflightError, check_device


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu",
                     help="torch device of the tests marked cuda (make gpu-check: cuda)")


def pytest_configure(config: pytest.Config) -> None:
    try:
        check_device(config.getoption("--device"))
    except PreflightError as exc:
        raise pytest.UsageError(str(exc)) from exc


@pytest.fixture
def device(request: pytest.FixtureRequest) -> str:
    """The torch device of a ``cuda``-marked test (``--device``; default ``cpu``)."""
    return request.config.getoption("--device")
