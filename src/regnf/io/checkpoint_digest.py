"""A checkpoint's content digest: SHA-256 of its header and of every tensor, computed from the
file as stored or from the tensors before they are saved, and checked on load
(:mod:`regnf.io.checkpoint`)."""

from __future__ import annotations

import hashlib
import io
import json
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO

import torch
from safetensors.torch import save as save_to_bytes

from regnf.io.checkpoint_checks import CheckpointError

HEADER_KEY = "regnf"
"""Key of the JSON header in the safetensors metadata."""

DIGEST_KEY = "sha256"
"""Header key of the content digest (64 lowercase hex digits)."""


_DIGEST_DOMAIN = b"regnf.checkpoint.sha256/2\n"
"""Prefix of every digest, so that it never equals a hash of anything else."""

_CHUNK = 1 << 20
"""Bytes hashed at a time: a checkpoint of any size is verified in constant memory."""


def content_digest(header: Mapping, tensors: Mapping[str, torch.Tensor]) -> str:
    """The :data:`DIGEST_KEY` of a checkpoint made of ``header`` and ``tensors``.

    Parameters
    ----------
    header : Mapping
        The JSON header (its own :data:`DIGEST_KEY`, if any, is left out of the digest).
    tensors : Mapping[str, torch.Tensor]
        Contiguous CPU tensors, as they will be saved.

    Returns
    -------
    str
        64 hex digits: SHA-256 of the canonical JSON of the header and of every tensor's name,
        dtype, shape and bytes, in name order. Equal to :func:`checkpoint_digest` of the file
        that :func:`save_field` writes; the tensors are serialised by safetensors here so that
        both hash the very same bytes with one implementation.
    """
    blob = save_to_bytes(dict(tensors), metadata={HEADER_KEY: json.dumps(dict(header))})
    return _serialised_digest(io.BytesIO(blob), len(blob), Path("<checkpoint in memory>"))


def checkpoint_digest(path: str | os.PathLike) -> str:
    """The digest of the checkpoint file at ``path`` as stored (see :func:`content_digest`).

    Reads the file once, :data:`_CHUNK` bytes at a time; builds nothing.

    Raises
    ------
    CheckpointError
        Unreadable, truncated, or not a safetensors file with a ``regnf`` header.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _serialised_digest(f, os.fstat(f.fileno()).st_size, path)
    except OSError as exc:
        raise CheckpointError(path, f"cannot read the file ({exc})") from exc


def _serialised_digest(f: BinaryIO, size: int, where: Path) -> str:
    """SHA-256 of a serialised checkpoint read from ``f`` (``size`` bytes); see content_digest."""
    def corrupt(what: str) -> CheckpointError:
        return CheckpointError(where, f"not a readable safetensors file ({what})")

    raw = f.read(8)
    if len(raw) < 8:
        raise corrupt("shorter than its header length")
    n = int.from_bytes(raw, "little")
    if n > size - 8:
        raise corrupt(f"header length {n} beyond the end of the file")
    try:
        index = json.loads(f.read(n))
        header = json.loads(index.pop("__metadata__")[HEADER_KEY])
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as exc:
        raise corrupt(f"no readable '{HEADER_KEY}' header: {exc}") from exc
    if not isinstance(header, dict):
        raise CheckpointError(where, "the JSON header is not an object")
    h = hashlib.sha256(_DIGEST_DOMAIN)
    canonical = json.dumps(
        {k: v for k, v in header.items() if k != DIGEST_KEY}, sort_keys=True, separators=(",", ":")
    ).encode()
    # Length prefixes make the concatenation unambiguous (no two inputs share a byte stream).
    h.update(len(canonical).to_bytes(8, "little") + canonical)
    base = 8 + n
    for name in sorted(index):
        entry = index[name]
        try:
            start, end = (int(v) for v in entry["data_offsets"])
            record = json.dumps([name, str(entry["dtype"]), [int(d) for d in entry["shape"]], end - start])
        except (KeyError, TypeError, ValueError) as exc:
            raise corrupt(f"bad index entry for tensor '{name}'") from exc
        if not 0 <= start <= end or base + end > size:
            raise CheckpointError(where, f"truncated or corrupted tensor data (tensor '{name}' ends beyond the file)")
        h.update(len(record).to_bytes(8, "little") + record.encode())
        f.seek(base + start)
        remaining = end - start
        while remaining:
            chunk = f.read(min(remaining, _CHUNK))
            if not chunk:
                raise CheckpointError(where, f"truncated or corrupted tensor data (tensor '{name}')")
            h.update(chunk)
            remaining -= len(chunk)
    return h.hexdigest()


STABLE_SECONDS = 2.0
"""A file last modified at least this long before its digest was computed is not hashed again
in this process while its identity (:func:`_file_identity`) stays the same."""
_VERIFIED: dict[tuple[int, ...], str] = {}
"""File identity -> the digest that the file was found to have (see :func:`check_digest`)."""


def _file_identity(path: Path) -> tuple[int, ...] | None:
    """(device, inode, size, mtime, ctime) of ``path``, or None if it cannot be stated."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def check_digest(path: Path, header: dict) -> None:
    """Compare the digest the header records (:func:`regnf.io.checkpoint.read_header` checked its
    form) with the file's.

    A stage is read many times in one run (every render step, every variant's layer) and
    its scene field alone is over 100 MB: a file whose digest this process has already checked
    is not hashed again while its device, inode, size and modification and change times stay
    the same. Any write changes the modification time (and a replacing rename the inode), but
    file systems keep those times at a coarse grain (milliseconds), so a file modified within
    :data:`STABLE_SECONDS` of the check is never remembered: a write that follows so soon could
    leave every field of the identity as it was (the "racily clean" case of git's index).
    """
    want = header[DIGEST_KEY]
    before = _file_identity(path)  # stated BEFORE hashing: a write during it changes the identity
    if before is not None and _VERIFIED.get(before) == want:
        return
    checked_at = time.time()
    got = checkpoint_digest(path)
    if got == want and before is not None and checked_at - max(before[3], before[4]) / 1e9 >= STABLE_SECONDS:
        _VERIFIED[before] = got
    if got != want:
        raise CheckpointError(
            path,
            f"content digest mismatch (header sha256 {want[:16]}..., file {got[:16]}...): the file "
            "was corrupted or edited after it was saved; retrain or copy it again",
        )
