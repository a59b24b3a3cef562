"""Checkpoints inside a .usdz package, carried by USD layers.

The usdz specification admits only USD layers, images and audio in a package, so a
``.safetensors`` file inside one is an error for OpenUSD's FileExtensionValidator. A package
therefore stores every checkpoint as a USD layer of its own (``fields/dc.safetensors`` becomes
``fields/dc.usdc``) whose default prim holds the file's bytes in a ``uchar[]`` attribute with
their SHA-256, and the packaged layers' checkpoint asset paths point at those layers. Reading
one back checks the digest and gives the original bytes, which are then validated like any
checkpoint file.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path, PurePosixPath

import numpy as np
from pxr import Sdf, Vt

from .errors import StageError

PRIM = "Checkpoint"
"""Default prim of an embedded-checkpoint layer."""
A_BYTES = "regnf:checkpoint:safetensors"
"""``uchar[]``: the checkpoint file, byte for byte."""
A_SHA256 = "regnf:checkpoint:sha256"
"""Hex SHA-256 of those bytes."""
CHECKPOINT_SUFFIX = ".safetensors"


def embedded_name(rel: str) -> str:
    """Package path of the layer that carries checkpoint ``rel`` (same folder, ``.usdc``)."""
    return str(PurePosixPath(rel).with_suffix(".usdc"))


def is_embedded(identifier: str) -> bool:
    """Whether a resolved checkpoint identifier is an embedded-checkpoint layer."""
    inner = identifier[identifier.index("[") + 1: -1] if identifier.endswith("]") and "[" in identifier \
        else identifier
    return inner.endswith(".usdc")


def write_embedded_checkpoint(checkpoint: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Write the layer (usdc) carrying ``checkpoint``'s bytes to ``dest``."""
    data = Path(checkpoint).read_bytes()
    layer = Sdf.Layer.CreateNew(str(dest))
    prim = Sdf.PrimSpec(layer, PRIM, Sdf.SpecifierDef)
    attr = Sdf.AttributeSpec(prim, A_BYTES, Sdf.ValueTypeNames.UCharArray)
    attr.default = Vt.UCharArray.FromNumpy(np.frombuffer(data, dtype=np.uint8))
    Sdf.AttributeSpec(prim, A_SHA256, Sdf.ValueTypeNames.String).default = hashlib.sha256(data).hexdigest()
    layer.defaultPrim = PRIM
    layer.Save()
    return Path(dest)


def read_embedded_checkpoint(identifier: str) -> bytes:
    """The checkpoint bytes held by the layer at ``identifier`` (digest checked).

    Raises
    ------
    StageError
        The layer cannot be opened, lacks the attributes, or its bytes do not match the digest.
    """
    layer = Sdf.Layer.FindOrOpen(identifier)
    if layer is None:
        raise StageError(identifier, "/", "the embedded checkpoint layer cannot be opened")
    where = f"/{PRIM}"
    prim = layer.GetPrimAtPath(where)
    attrs = prim.attributes if prim else {}
    if not prim or A_BYTES not in attrs or A_SHA256 not in attrs:
        raise StageError(identifier, where, f"not an embedded checkpoint (needs {A_BYTES} and {A_SHA256})")
    data = np.asarray(attrs[A_BYTES].default, dtype=np.uint8).tobytes()
    if hashlib.sha256(data).hexdigest() != attrs[A_SHA256].default:
        raise StageError(identifier, where, "the embedded checkpoint is corrupted (SHA-256 mismatch)")
    return data


@contextlib.contextmanager
def checkpoint_file(identifier: str | os.PathLike) -> Iterator[Path]:
    """A checkpoint file for ``identifier``: the file itself, or the embedded bytes written to a
    temporary ``.safetensors`` (removed on exit)."""
    ident = str(identifier)
    if not is_embedded(ident):
        yield Path(ident)
        return
    data = read_embedded_checkpoint(ident)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "embedded.safetensors"
        path.write_bytes(data)
        yield path
