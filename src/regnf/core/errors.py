"""The base of regnf's own errors: a problem with what the user gave, named in one line.

The command line reports a :class:`RegnfError` (and an ``OSError``: a missing file, a full disk)
as bad input, exit status 1, in one line; any other exception is a bug in regnf, reported as an
internal error (exit status 70) whose traceback ``--debug`` shows. It is a ``ValueError``, so
code that catches bad values catches it too.
"""

from __future__ import annotations


class RegnfError(ValueError):
    """A problem with regnf's input (a file, an option, a stage), its message naming it in one line."""


def is_regnf_error_name(name: str) -> bool:
    """Whether ``name`` is the class name of :class:`RegnfError` or of a subclass loaded in this
    process: an error that came back from a worker process as text (``"CheckpointError: ..."``)."""
    classes = [RegnfError]
    while classes:
        cls = classes.pop()
        if cls.__name__ == name:
            return True
        classes += cls.__subclasses__()
    return False
