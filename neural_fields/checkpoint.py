"""Checkpoints: safetensors weights plus a JSON header, validated on load. Never pickle.

The JSON header lives in the safetensors metadata under the key ``regnf`` and records the
architecture, bounds, ``to_world``, class, symmetry and provenance, so one file is the
whole field and a reader can check every tensor before building anything.

Nothing in a checkpoint is trusted:

- the header is checked before anything is built or allocated (:func:`read_header`): its
  format version, the architecture's types and sizes against :class:`ArchitectureLimits`,
  ``bounds`` (min < max) and ``to_world`` (a similarity with a positive uniform scale and a
  proper rotation);
- the header records ``sha256``, the SHA-256 of the rest of the header and of every tensor
  (name, dtype, shape, bytes), written by :func:`save_field` and compared on load, so a
  flipped bit anywhere is refused even where it leaves a finite number;
  :func:`verify_checkpoint` checks it without building the field (for stage readers);
- quantities stored twice, in the header and as a buffer in the weights (:data:`STORED_TWICE`),
  must agree exactly.

A field that records where its training views observed space (``field.visibility``, see
:mod:`regnf.neural_fields.visibility`) stores the grid's counts as the tensor ``visibility.counts``
(uint8) and its metadata as the header's ``visibility`` block (null without one). Both are
covered by the digest and checked on load: the block's types, its resolution against
:class:`ArchitectureLimits` before anything is read, the tensor's shape against the block and
its dtype. :func:`attach_visibility` adds a grid to a checkpoint from the capture it was
trained on, without retraining. The grid is optional, so files without it (format 2 files
written before grids existed have no ``visibility`` key) still load, with
``visibility = None``; the format version stays 2.

Format versions: 2 (this one) added the digest. Version-1 files carry none, so nothing proves
their weights are the ones that were saved: :func:`read_header`, :func:`load_field` and
:func:`verify_checkpoint` refuse them with a message saying to retrain the field (the cache,
:data:`regnf.neural_fields.cache.CACHE_VERSION` 3, remakes its own) or to re-save it:
``save_field(load_field(path, allow_legacy=True), path)`` loads it with every other check and
writes it as version 2.

Every failure is a :class:`CheckpointError` whose one-line message names the file and the
problem (and the tensor or header key).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, NamedTuple

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as save_to_bytes

from regnf.core.atomic_io import write_bytes
from regnf.core.preflight import input_file_problem
from regnf.neural_fields.field import FieldInfo, Symmetry
from regnf.neural_fields.neural_sdf import ARCHITECTURE, NeuralSDF, NeuralSDFConfig, parameter_count
from regnf.neural_fields.rgbd_samples import CaptureLike, capture_where
from regnf.neural_fields.similarity import decompose_similarity
from regnf.neural_fields.visibility import (
    DEFAULT_MARGIN,
    DEFAULT_RESOLUTION,
    VisibilityGrid,
    build_visibility,
)

HEADER_KEY = "regnf"
"""Key of the JSON header in the safetensors metadata."""

FORMAT_VERSION = 2
"""Written by :func:`save_field`. 2: the header records :data:`DIGEST_KEY`."""

LEGACY_FORMAT_VERSIONS = (1,)
"""Older versions: refused unless ``allow_legacy=True`` (see the module docstring)."""

DIGEST_KEY = "sha256"
"""Header key of the content digest (64 lowercase hex digits)."""

VISIBILITY_KEY = "visibility"
"""Header key of the visibility grid's metadata (:meth:`VisibilityGrid.to_json`), or null."""

VISIBILITY_TENSOR = "visibility.counts"
"""Name of the visibility grid's counts, (R_x, R_y, R_z) uint8, when the header has a grid."""

STORED_TWICE = {"bounds": "bounds", "to_world": "to_world"}
"""Header keys that the weights also hold as a buffer (header key -> tensor name). A reader of
the header alone (a stage) and the loaded field must see the same numbers, so the two copies
must be equal (compared in float64, which holds both exactly)."""

# -- limits on the architecture a header may ask for --------------------------------------
# A header is checked against these before any model (not even a weightless meta-device
# skeleton, which builds one module per level and per layer) is constructed: a forged
# ``levels = 10**8`` otherwise loops for minutes, and a forged size allocates gigabytes.
# Each is far above anything regnf trains; pass ``ArchitectureLimits(...)`` to go beyond.

MAX_LEVELS = 32
"""Grid levels (presets: 6-7; instant-NGP: 16). Levels are a geometric series from the base
to the finest resolution: beyond 32 they are a few percent apart and only cost memory."""

MAX_HIDDEN_LAYERS = 64
"""Hidden layers of the SDF MLP (presets: 2). One module each."""

MAX_WIDTH = 4096
"""``hidden_dim``, ``geo_feature_dim`` and ``color_hidden_dim`` (presets: 64, 15, 64)."""

MAX_FEATURES_PER_LEVEL = 64
"""Feature channels per grid level (presets: 4; instant-NGP: 2)."""

MAX_RESOLUTION = 2**16
"""``base_resolution`` and ``finest_resolution``, cells along the longest axis (presets: up
to 256). Also keeps the hash encoding's integer corner products far from int64 overflow."""

MAX_HASH_TABLE_SIZE_LOG2 = 26
"""Hash encoding: at most 2**26 rows per level (instant-NGP: 2**19 to 2**24)."""

MAX_PARAMETERS = 2**28
"""Trainable values in all (268 M, 1 GiB of float32; presets: 4 M for an object, about 30 M
for a room). Bounds what building the field allocates, whatever the other values combine to."""

MAX_VISIBILITY_RESOLUTION = 1024
"""Voxels along any axis of a visibility grid (training's default: 128 on the longest)."""

MAX_VISIBILITY_VOXELS = 2**26
"""Voxels of a visibility grid in all (67 M: 64 MiB of uint8 counts and the 256 MiB float32
lookup volume built on load; training's default: at most 2.1 M)."""


@dataclass(frozen=True)
class ArchitectureLimits:
    """The largest architecture a checkpoint header may ask for (defaults: the MAX_* constants)."""

    max_levels: int = MAX_LEVELS
    """See :data:`MAX_LEVELS`."""
    max_hidden_layers: int = MAX_HIDDEN_LAYERS
    """See :data:`MAX_HIDDEN_LAYERS`."""
    max_width: int = MAX_WIDTH
    """See :data:`MAX_WIDTH`."""
    max_features_per_level: int = MAX_FEATURES_PER_LEVEL
    """See :data:`MAX_FEATURES_PER_LEVEL`."""
    max_resolution: int = MAX_RESOLUTION
    """See :data:`MAX_RESOLUTION`."""
    max_hash_table_size_log2: int = MAX_HASH_TABLE_SIZE_LOG2
    """See :data:`MAX_HASH_TABLE_SIZE_LOG2`."""
    max_parameters: int = MAX_PARAMETERS
    """See :data:`MAX_PARAMETERS`."""
    max_visibility_resolution: int = MAX_VISIBILITY_RESOLUTION
    """See :data:`MAX_VISIBILITY_RESOLUTION`."""
    max_visibility_voxels: int = MAX_VISIBILITY_VOXELS
    """See :data:`MAX_VISIBILITY_VOXELS`."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the one-line message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = Path(path)
        # One line, even when the problem quotes a library's multi-line message.
        self.problem = re.sub(r"\s*[\r\n]+\s*", " ", problem)
        super().__init__(f"{self.path}: {self.problem}")


def check_architecture(
    config: NeuralSDFConfig, extent: torch.Tensor, limits: ArchitectureLimits | None = None
) -> int:
    """Refuse an architecture beyond ``limits``, cheaply (nothing is built or allocated).

    Parameters
    ----------
    config : NeuralSDFConfig
        A parsed (type-checked) config.
    extent : (3,) float
        Size of the field's bounds box (its aspect ratio sets the dense grids' shapes).
    limits : ArchitectureLimits, optional
        Defaults to the module's MAX_* constants.

    Returns
    -------
    int
        The field's number of trainable values.

    Raises
    ------
    ValueError
        Naming the first value over its limit, or the parameter count.
    """
    lim = limits or ArchitectureLimits()
    bounded = [
        ("levels", config.levels, lim.max_levels, "max_levels"),
        ("hidden_layers", config.hidden_layers, lim.max_hidden_layers, "max_hidden_layers"),
        ("hidden_dim", config.hidden_dim, lim.max_width, "max_width"),
        ("geo_feature_dim", config.geo_feature_dim, lim.max_width, "max_width"),
        ("color_hidden_dim", config.color_hidden_dim, lim.max_width, "max_width"),
        ("features_per_level", config.features_per_level, lim.max_features_per_level,
         "max_features_per_level"),
        ("base_resolution", config.base_resolution, lim.max_resolution, "max_resolution"),
        ("finest_resolution", config.finest_resolution, lim.max_resolution, "max_resolution"),
        ("hash_table_size_log2", config.hash_table_size_log2, lim.max_hash_table_size_log2,
         "max_hash_table_size_log2"),
    ]
    for name, value, limit, knob in bounded:
        if value > limit:
            raise ValueError(f"{name} = {value} exceeds the limit {limit} (ArchitectureLimits.{knob})")
    count = parameter_count(config, extent)  # one step per level: levels is bounded above
    if count > lim.max_parameters:
        raise ValueError(
            f"{count} parameters exceed the limit {lim.max_parameters} (ArchitectureLimits.max_parameters)"
        )
    return count


def check_visibility(meta: Mapping, limits: ArchitectureLimits | None = None) -> int:
    """Refuse a visibility grid beyond ``limits``, from its parsed metadata (nothing allocated).

    Parameters
    ----------
    meta : Mapping
        :meth:`VisibilityGrid.parse_json` of the header's block.
    limits : ArchitectureLimits, optional
        Defaults to the module's MAX_* constants.

    Returns
    -------
    int
        The grid's number of voxels.

    Raises
    ------
    ValueError
        Naming the axis or the voxel count over its limit.
    """
    lim = limits or ArchitectureLimits()
    resolution = meta["resolution"]
    for axis, n in zip("xyz", resolution):
        if n > lim.max_visibility_resolution:
            raise ValueError(
                f"{n} voxels along {axis} exceed the limit {lim.max_visibility_resolution} "
                "(ArchitectureLimits.max_visibility_resolution)"
            )
    voxels = math.prod(resolution)
    if voxels > lim.max_visibility_voxels:
        raise ValueError(
            f"{voxels} voxels exceed the limit {lim.max_visibility_voxels} "
            "(ArchitectureLimits.max_visibility_voxels)"
        )
    return voxels


def field_header(field: NeuralSDF) -> dict:
    """The JSON header describing ``field`` (everything but the weights and the digest)."""
    visibility = getattr(field, "visibility", None)
    return {
        "format_version": FORMAT_VERSION,
        "architecture": ARCHITECTURE,
        "config": field.config.to_json(),
        "bounds": field.bounds.tolist(),
        "to_world": field.to_world.tolist(),
        "label": field.info.label,
        "name": field.info.name,
        "symmetry": field.info.symmetry.to_json(),
        "provenance": field.info.provenance,
        VISIBILITY_KEY: None if visibility is None else visibility.to_json(),
    }


# -- the content digest ---------------------------------------------------------------------

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
"""File identity -> the digest that the file was found to have (see :func:`_check_digest`)."""


def _file_identity(path: Path) -> tuple[int, ...] | None:
    """(device, inode, size, mtime, ctime) of ``path``, or None if it cannot be stated."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _check_digest(path: Path, header: dict) -> None:
    """Compare the digest the header records with the file's (no-op for a legacy header).

    A stage is read many times in one run (every render step, every variant's layer) and
    its scene field alone is over 100 MB: a file whose digest this process has already checked
    is not hashed again while its device, inode, size and modification and change times stay
    the same. Any write changes the modification time (and a replacing rename the inode), but
    file systems keep those times at a coarse grain (milliseconds), so a file modified within
    :data:`STABLE_SECONDS` of the check is never remembered: a write that follows so soon could
    leave every field of the identity as it was (the "racily clean" case of git's index).
    """
    want = header.get(DIGEST_KEY)
    if want is None:
        return  # a legacy file read with allow_legacy=True
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


def _check_stored_twice(path: Path, header: dict, tensors: Mapping[str, torch.Tensor]) -> None:
    """Refuse a buffer that disagrees with its header copy (see :data:`STORED_TWICE`)."""
    for key, name in STORED_TWICE.items():
        stored = tensors[name].to(torch.float64)
        declared = torch.tensor(header[key], dtype=torch.float64)
        if stored.shape != declared.shape:
            raise CheckpointError(
                path, f"tensor '{name}' has shape {tuple(stored.shape)}, the header's '{key}' {tuple(declared.shape)}"
            )
        if not torch.equal(stored, declared):
            diff = float((stored - declared).abs().nan_to_num(math.inf).max())
            raise CheckpointError(
                path,
                f"tensor '{name}' disagrees with the header's '{key}' (largest difference {diff:.6g}); "
                "the file was edited or corrupted",
            )


# -- the header -------------------------------------------------------------------------------


class _Parsed(NamedTuple):
    """What a validated header describes."""

    config: NeuralSDFConfig
    bounds: torch.Tensor
    """(2, 3) float32."""
    to_world: torch.Tensor
    """(4, 4) float64."""
    info: FieldInfo
    visibility: dict | None
    """:meth:`VisibilityGrid.parse_json` of the header's block; None without a grid."""


def _read(
    path: Path, limits: ArchitectureLimits | None, allow_legacy: bool
) -> tuple[dict, _Parsed]:
    """Read the header of ``path`` and validate everything it says; see :func:`read_header`."""
    problem = input_file_problem(path, missing="file does not exist")
    if problem is not None:
        raise CheckpointError(path, problem)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(path, f"not a readable safetensors file ({exc})") from exc
    if HEADER_KEY not in meta:
        raise CheckpointError(path, f"no '{HEADER_KEY}' JSON header (not a regnf checkpoint)")
    try:
        header = json.loads(meta[HEADER_KEY])
    except json.JSONDecodeError as exc:
        raise CheckpointError(path, f"the JSON header is corrupted ({exc})") from exc
    if not isinstance(header, dict):
        raise CheckpointError(path, "the JSON header is not an object")
    _check_version(path, header.get("format_version"), allow_legacy)
    arch = header.get("architecture")
    if arch != ARCHITECTURE:
        raise CheckpointError(path, f"unknown architecture {arch!r} (expected {ARCHITECTURE!r})")
    for key in ("config", "bounds", "to_world"):
        if key not in header:
            raise CheckpointError(path, f"the header lacks '{key}'")
    header_contents = _parse(path, header, limits)
    if header["format_version"] == FORMAT_VERSION:
        digest = header.get(DIGEST_KEY)
        if not (isinstance(digest, str) and len(digest) == 64 and all(c in "0123456789abcdef" for c in digest)):
            raise CheckpointError(path, f"the header's '{DIGEST_KEY}' must be 64 hex digits, got {digest!r}")
    return header, header_contents


def _parse(path: Path, header: dict, limits: ArchitectureLimits | None) -> _Parsed:
    """Validate what a header says about the field (not the file around it) and parse it.

    Shared by the readers and by :func:`save_field`, so that a file is written only if it
    will be read back.
    """
    bounds = _matrix(path, "bounds", header["bounds"], (2, 3))
    if not bool((bounds[1] > bounds[0]).all()):
        raise CheckpointError(path, f"'bounds' must have min < max on every axis, got {bounds.tolist()}")
    to_world = _matrix(path, "to_world", header["to_world"], (4, 4))
    try:
        decompose_similarity(to_world)
    except ValueError as exc:
        raise CheckpointError(
            path, f"'to_world' is not a similarity (positive uniform scale, rotation): {exc}"
        ) from exc
    try:
        config = NeuralSDFConfig.from_json(header["config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(path, f"bad architecture config: {exc}") from exc
    try:
        check_architecture(config, bounds[1] - bounds[0], limits)
    except ValueError as exc:
        raise CheckpointError(path, f"architecture refused: {exc}") from exc
    visibility = None
    if header.get(VISIBILITY_KEY) is not None:  # absent in files written before grids existed
        try:
            visibility = VisibilityGrid.parse_json(header[VISIBILITY_KEY])
        except (TypeError, ValueError) as exc:
            raise CheckpointError(path, f"bad '{VISIBILITY_KEY}' block: {exc}") from exc
        try:
            check_visibility(visibility, limits)
        except ValueError as exc:
            raise CheckpointError(path, f"visibility grid refused: {exc}") from exc
    return _Parsed(config, bounds.float(), to_world, _field_info(path, header), visibility)


def _expected_visibility(parsed: _Parsed) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """The visibility tensor a header asks for (name -> (shape, dtype)); empty without a grid."""
    if parsed.visibility is None:
        return {}
    return {VISIBILITY_TENSOR: (tuple(parsed.visibility["resolution"]), torch.uint8)}


def _check_version(path: Path, version: object, allow_legacy: bool) -> None:
    if version == FORMAT_VERSION or (allow_legacy and version in LEGACY_FORMAT_VERSIONS):
        return
    if version in LEGACY_FORMAT_VERSIONS:
        raise CheckpointError(
            path,
            f"format version {version} has no content digest and is no longer trusted; retrain the "
            "field (cached fields are remade) or re-save it: "
            "save_field(load_field(path, allow_legacy=True), path)",
        )
    raise CheckpointError(
        path, f"unsupported format version {version!r} (this regnf reads version {FORMAT_VERSION})"
    )


def _field_info(path: Path, header: dict) -> FieldInfo:
    """The label, name, symmetry and provenance of a header, type-checked."""
    expected = {"label": (str, "a string"), "name": (str, "a string"), "provenance": (dict, "an object"),
                "symmetry": ((dict, type(None)), "an object")}
    for key, (kind, words) in expected.items():
        if key in header and not isinstance(header[key], kind):
            raise CheckpointError(path, f"bad header: '{key}' must be {words}, got {header[key]!r:.80}")
    try:
        return FieldInfo(
            label=header.get("label", "object"),
            name=header.get("name", ""),
            symmetry=Symmetry.from_json(header.get("symmetry")),
            provenance=dict(header.get("provenance", {})),
        )
    except (TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(path, f"bad header: {exc}") from exc


def read_header(
    path: str | os.PathLike, limits: ArchitectureLimits | None = None, allow_legacy: bool = False
) -> dict:
    """Read and validate the JSON header of a checkpoint without loading weights.

    Cheap (reads the safetensors header only) and safe on hostile files: the architecture is
    bounded by ``limits`` before anything could build it.

    Parameters
    ----------
    path : str or PathLike
    limits : ArchitectureLimits, optional
        The largest architecture accepted (default: the MAX_* constants).
    allow_legacy : bool
        Accept a version-1 header (no digest); see the module docstring.

    Returns
    -------
    dict
        The header as stored, :data:`DIGEST_KEY` included.

    Raises
    ------
    CheckpointError
        Missing or unreadable file, no or corrupted header, an unsupported (or, without
        ``allow_legacy``, legacy) format version, unknown architecture, a config of the
        wrong types or beyond ``limits``, bounds with min >= max, a ``to_world`` that is not
        a similarity, badly typed label / name / symmetry / provenance, a malformed digest,
        a ``visibility`` block of the wrong types or beyond ``limits``.
        The digest itself is compared by :func:`verify_checkpoint` and :func:`load_field`.
    """
    return _read(Path(path), limits, allow_legacy)[0]


def verify_checkpoint(path: str | os.PathLike, limits: ArchitectureLimits | None = None) -> dict:
    """Check a checkpoint's integrity without building the field; returns its header.

    :func:`read_header`'s checks, the content digest (the whole file is hashed, in constant
    memory), the tensors :data:`STORED_TWICE` against the header, and the visibility counts'
    presence, shape and dtype against the header's ``visibility`` block. What it does not do is
    :func:`load_field`'s tensor-by-tensor validation against the architecture, which needs
    the model: a file that passes here was written by :func:`save_field` and not altered.

    Raises
    ------
    CheckpointError
        Any of :func:`read_header`'s, a digest mismatch (corrupted or edited file), a
        buffer that disagrees with its header copy, or visibility counts missing, unexpected,
        or of another shape or dtype than the header's block says. Legacy (version-1) files
        are refused.
    """
    path = Path(path)
    header, parsed = _read(path, limits, allow_legacy=False)
    _check_digest(path, header)
    visibility = _expected_visibility(parsed)
    try:
        with safe_open(str(path), framework="pt") as f:
            names = set(f.keys())
            missing = sorted(set(STORED_TWICE.values()) - names)
            if missing:
                raise CheckpointError(path, f"missing tensors {missing}")
            _check_visibility_tensor(path, visibility, names, f)
            tensors = {name: f.get_tensor(name) for name in STORED_TWICE.values()}
    except CheckpointError:
        raise
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(path, f"truncated or corrupted tensor data ({exc})") from exc
    _check_stored_twice(path, header, tensors)
    return header


_SAFETENSORS_DTYPES = {torch.uint8: "U8"}
"""How safetensors names the dtypes checked from a tensor's index entry."""


def _check_visibility_tensor(
    path: Path,
    expected: Mapping[str, tuple[tuple[int, ...], torch.dtype]],
    names: set[str],
    f: object,
) -> None:
    """The visibility counts are stored iff the header has a grid, with its shape and dtype.

    ``expected`` is :func:`_expected_visibility`, ``names`` the file's tensors, ``f`` the open
    ``safe_open`` handle (only index entries are read).
    """
    if not expected:
        if VISIBILITY_TENSOR in names:
            raise CheckpointError(
                path, f"unexpected tensors ['{VISIBILITY_TENSOR}'] (the header has no visibility grid)"
            )
        return
    ((name, (shape, dtype)),) = expected.items()
    if name not in names:
        raise CheckpointError(path, f"missing tensors ['{name}'] (the header has a visibility grid)")
    entry = f.get_slice(name)  # type: ignore[attr-defined]
    stored = tuple(entry.get_shape())
    if stored != shape:
        raise CheckpointError(
            path, f"tensor '{name}' has shape {stored}, the header's visibility resolution {list(shape)}"
        )
    want = _SAFETENSORS_DTYPES[dtype]
    if entry.get_dtype() != want:
        raise CheckpointError(path, f"tensor '{name}' has dtype {entry.get_dtype()}, expected {want}")


# -- saving and loading ------------------------------------------------------------------------


def save_field(
    field: NeuralSDF, path: str | os.PathLike, limits: ArchitectureLimits | None = None
) -> Path:
    """Write ``field`` to ``path`` (``.safetensors``) atomically, with its digest; returns the path.

    The header is validated as a reader will validate it (``limits`` as for loading), so a
    file this writes loads. The file gets the user's umask (``0o666 & ~umask``).

    Raises
    ------
    CheckpointError
        A wrong suffix, or a field whose header a reader would refuse (e.g. a ``to_world``
        that is not a similarity); nothing is written then.
    """
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(path, "checkpoints are .safetensors files")
    # JSON-normalised (tuples -> lists, ...): exactly what a reader will parse and hash.
    header = json.loads(json.dumps(field_header(field)))
    _parse(path, header, limits)
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in field.state_dict().items()}
    header[DIGEST_KEY] = content_digest(header, tensors)
    # Serialised in memory and written by atomic_io: safetensors' own save_file renames a
    # private (0600) temporary of its own over the destination, which a kill leaves behind
    # under a name that is not ours to clean up.
    write_bytes(path, save_to_bytes(tensors, metadata={HEADER_KEY: json.dumps(header)}))
    return path


def load_field(
    path: str | os.PathLike,
    device: torch.device | str = "cpu",
    limits: ArchitectureLimits | None = None,
    allow_legacy: bool = False,
) -> NeuralSDF:
    """Load a checkpoint written by :func:`save_field`, validating every tensor.

    Parameters
    ----------
    path : str or PathLike
    device : torch.device or str
        Where the field is moved after loading.
    limits : ArchitectureLimits, optional
        The largest architecture accepted (default: the MAX_* constants).
    allow_legacy : bool
        Load a version-1 file (no digest: every other check still applies), e.g. to re-save
        it with :func:`save_field`.

    Raises
    ------
    CheckpointError
        Any of :func:`read_header`'s; missing / unexpected tensors, wrong shapes or dtypes, a
        content digest mismatch, non-finite weights, a buffer that disagrees with its header
        copy (``to_world``, ``bounds``). The field's ``visibility`` is the stored grid, or None
        when the header has none.
    """
    path = Path(path)
    header, parsed = _read(path, limits, allow_legacy)
    config, bounds, to_world, info, visibility = parsed
    try:
        # Build a weightless skeleton first (meta device: nothing is allocated), so that the
        # stored shapes are compared before the real field allocates anything. The header's
        # sizes are already bounded, so building it is quick too.
        with torch.device("meta"):
            skeleton = NeuralSDF(config, bounds=bounds, to_world=to_world, info=info)
    except (TypeError, ValueError, AttributeError, RuntimeError) as exc:
        raise CheckpointError(path, f"cannot build the field from the header: {exc}") from exc
    expected = {k: (tuple(v.shape), v.dtype) for k, v in skeleton.state_dict().items()}
    expected.update(_expected_visibility(parsed))
    try:
        with safe_open(str(path), framework="pt") as f:
            names = set(f.keys())
            missing = sorted(set(expected) - names)
            extra = sorted(names - set(expected))
            if missing:
                raise CheckpointError(path, f"missing tensors {missing[:5]}")
            if extra:
                raise CheckpointError(path, f"unexpected tensors {extra[:5]}")
            for name, (shape, _) in expected.items():
                stored = tuple(f.get_slice(name).get_shape())
                if stored != shape:
                    raise CheckpointError(path, f"tensor '{name}' has shape {stored}, expected {shape}")
            # Sizes are right: hash the whole file before trusting any value in it.
            _check_digest(path, header)
            state = {}
            for name, (_, dtype) in expected.items():
                t = f.get_tensor(name)
                if t.dtype != dtype:
                    raise CheckpointError(path, f"tensor '{name}' has dtype {t.dtype}, expected {dtype}")
                if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                    raise CheckpointError(path, f"tensor '{name}' has non-finite values")
                state[name] = t
    except CheckpointError:
        raise
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(path, f"truncated or corrupted tensor data ({exc})") from exc
    _check_stored_twice(path, header, state)
    counts = state.pop(VISIBILITY_TENSOR, None)
    # The skeleton takes the stored tensors as they are: building a second field would
    # initialise every grid at random only to overwrite it (a second for a room's field).
    field = skeleton
    field.load_state_dict(state, assign=True)
    left = [n for n, t in [*field.named_parameters(), *field.named_buffers()] if t.is_meta]
    if left:  # every tensor of the state dict was checked above: a bug if it fires
        raise RuntimeError(f"{path}: tensors {left} were not loaded")
    if visibility is not None:
        meta = {k: v for k, v in visibility.items() if k != "resolution"}
        try:
            field.visibility = VisibilityGrid(counts, **meta)
        except ValueError as exc:  # parse_json checked every value: a bug if it fires
            raise CheckpointError(path, f"bad visibility grid: {exc}") from exc
    return field.to(device)


def attach_visibility(
    checkpoint_path: str | os.PathLike,
    capture: CaptureLike,
    out_path: str | os.PathLike | None = None,
    resolution: int = DEFAULT_RESOLUTION,
    margin: float = DEFAULT_MARGIN,
    pixel_stride: int = 1,
    device: torch.device | str = "cpu",
    indices: Sequence[int] | None = None,
    limits: ArchitectureLimits | None = None,
) -> Path:
    """Give a checkpoint the visibility grid of the capture it was trained on, without retraining.

    For fields trained elsewhere or before fields recorded visibility: the grid is built from
    ``capture``'s training frames over the field's bounds
    (:func:`regnf.neural_fields.visibility.build_visibility`), as
    :func:`regnf.neural_fields.training.train_rgbd` builds it, and replaces any grid the checkpoint
    had. Everything else (weights, header, provenance) is kept; the file is rewritten
    atomically with a new digest.

    Parameters
    ----------
    checkpoint_path : str or PathLike
        A checkpoint of a field trained on ``capture`` (it lives in the capture's normalised
        frame: its ``to_world`` is the capture's ``worldtogt``).
    capture : Capture
        The loaded capture (:func:`regnf.captures.formats.read_capture`).
    out_path : str or PathLike, optional
        Where to write the result; default: replace ``checkpoint_path``.
    resolution, margin, pixel_stride, device, indices
        As for :func:`regnf.neural_fields.visibility.build_visibility` (defaults: training's).
    limits : ArchitectureLimits, optional
        For loading and saving (default: the MAX_* constants).

    Returns
    -------
    Path
        The written checkpoint.

    Raises
    ------
    CheckpointError
        Any of :func:`load_field`'s or :func:`save_field`'s, or a field whose ``to_world`` is
        not the capture's ``worldtogt`` (its frame is not the capture's: the grid would not
        line up with it).
    CaptureError
        The capture has no training frame with depth, or a depth file is bad.
    """
    path = Path(checkpoint_path)
    field = load_field(path, limits=limits)
    worldtogt = torch.as_tensor(capture.worldtogt, dtype=torch.float64)  # type: ignore[attr-defined]
    # Training sets to_world to the capture's worldtogt exactly; a tolerance admits a
    # checkpoint that went through float32 elsewhere, not another frame.
    diff = float((field.to_world - worldtogt).abs().max())
    if not diff <= 1e-6 * (1.0 + float(worldtogt.abs().max())):
        raise CheckpointError(
            path,
            f"to_world differs from the worldtogt of {capture_where(capture)} by up to {diff:.3g}: "
            "the field does not live in this capture's normalised frame, so its visibility "
            "cannot be taken from it",
        )
    field.visibility = build_visibility(
        capture, field.bounds, resolution=resolution, margin=margin, pixel_stride=pixel_stride,
        device=device, indices=indices,
    )
    return save_field(field, path if out_path is None else out_path, limits)


def _matrix(path: Path, key: str, value: object, shape: tuple[int, int]) -> torch.Tensor:
    """``value`` as a finite float64 tensor of ``shape``, or a CheckpointError naming ``key``."""
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise CheckpointError(path, f"'{key}' is not a numeric matrix") from exc
    if tuple(t.shape) != shape:
        raise CheckpointError(path, f"'{key}' has shape {tuple(t.shape)}, expected {shape}")
    if not bool(torch.isfinite(t).all()):
        raise CheckpointError(path, f"'{key}' has non-finite values")
    return t
