"""The one error type of the scene graph: it names the file and the prim that are wrong."""

from __future__ import annotations

import os
from pathlib import Path

from regnf.core.errors import RegnfError


class StageError(RegnfError):
    """A stage that cannot be written or read; the message names the file, the prim and why.

    Parameters
    ----------
    path : str or PathLike
        The file at fault (a stage, an asset layer or a checkpoint).
    prim : str
        The prim path concerned (``/`` for the layer as a whole, empty for a path that is no
        readable file at all).
    problem : str
        What is wrong, in words.
    """

    def __init__(self, path: str | os.PathLike, prim: str, problem: str) -> None:
        self.path = Path(path)
        self.prim = prim
        self.problem = problem
        where = f"prim {prim}: " if prim else ""
        super().__init__(f"{self.path}: {where}{problem}")
