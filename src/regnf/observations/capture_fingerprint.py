"""The key of a trained field: a SHA-256 of the capture files its training read
(:mod:`regnf.synthetic.cache`)."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path

from regnf.captures.model import META_NAME, capture_file

FINGERPRINT_VERSION = b"regnf.capture-fingerprint/2\n"
"""Prefix of every capture fingerprint; changing how it is computed changes this."""

_CHUNK = 1 << 20
"""Bytes hashed at a time (captures hold hundreds of megabytes)."""


def capture_fingerprint(root: str | os.PathLike, files: Sequence[str | os.PathLike],
                        meta_name: str = META_NAME) -> str:
    """SHA-256 of a capture's training data: its metadata file and every file in ``files``.

    The key of a trained field: it depends on the bytes of the inputs and on their names
    inside the capture folder only, not on how the folder was named (relative, absolute,
    ``./x``, through a symlink) nor where it lies.

    Parameters
    ----------
    root : str or PathLike
        The capture folder.
    files : sequence of str or PathLike
        Files the training reads (images, depths); absolute, or relative to ``root``.
    meta_name : str
        The capture's metadata file in ``root`` (``Capture.meta_name``).

    Returns
    -------
    str
        64 hex digits.

    Raises
    ------
    CaptureError
        A file that does not exist or lies outside ``root`` (symlinks resolved): a key that
        silently skipped it would let another capture's field be reused.
    """
    root = Path(root)
    base = os.path.realpath(root)
    h = hashlib.sha256(FINGERPRINT_VERSION)
    for name in [meta_name, *files]:
        # The loader's rule: an existing file inside the folder (an absolute name stays as is).
        real = os.path.realpath(capture_file(root, os.fspath(name), f"{root / meta_name}: training input"))
        # Name and length first: the concatenation of (name, bytes) records is unambiguous.
        h.update(f"{Path(os.path.relpath(real, base)).as_posix()}\0{os.path.getsize(real)}\0".encode())
        with open(real, "rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
    return h.hexdigest()
