"""regnf's own errors: one base, recognised by name when they come back from a worker as text."""

from __future__ import annotations

from regnf.core.errors import RegnfError, is_regnf_error_name


def test_the_project_errors_derive_from_the_base_and_are_known_by_name() -> None:
    from regnf.captures.model import CaptureError
    from regnf.io.checkpoint import CheckpointError
    from regnf.scene_graph.errors import StageError

    for cls in (CaptureError, CheckpointError, StageError):
        assert issubclass(cls, RegnfError) and issubclass(cls, ValueError)
        assert is_regnf_error_name(cls.__name__)
    assert is_regnf_error_name("RegnfError")
    # A dependency's errors are not the project's: a worker's ValueError text is not one of them.
    for name in ("ValueError", "KeyError", "RuntimeError", "JSONDecodeError", ""):
        assert not is_regnf_error_name(name)
