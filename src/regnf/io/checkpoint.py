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
:mod:`regnf.observations.visibility`) stores the grid's counts as the tensor ``visibility.counts``
(uint8) and its metadata as the header's ``visibility`` block (null without one). Both are
covered by the digest and checked on load: the block's types, its resolution against
:class:`ArchitectureLimits` before anything is read, the tensor's shape against the block and
its dtype. :func:`attach_visibility` adds a grid to a checkpoint from the capture it was
trained on, without retraining. The grid is optional, so files without it (format 2 files
written before grids existed have no ``visibility`` key) still load, with
``visibility = None``; the format version stays 2.

Format versions: 2 (this one) added the digest. Version-1 files carry none, so nothing proves
their weights are the ones that were saved: :func:`read_header`, :func:`load_field` and
:func:`verify_checkpoint` refuse them with a message saying to retrain the field or to convert
it with ``scripts/convert_checkpoint_v1.py`` of the repository (outside the package), which
checks everything else in the file and writes it as version 2.

Every failure is a :class:`CheckpointError` whose one-line message names the file and the
problem (and the tensor or header key).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as save_to_bytes

from regnf.core.atomic_io import write_bytes
from regnf.core.fresh_memory import in_fresh_memory
from regnf.core.preflight import input_file_problem
from regnf.fields.field import FieldInfo, Symmetry
from regnf.fields.neural_sdf import ARCHITECTURE, NeuralSDF, NeuralSDFConfig
from regnf.fields.similarity import decompose_similarity
from regnf.io.checkpoint_checks import (
    ArchitectureLimits,
    CheckpointError,
    check_architecture,
    check_visibility,
)
from regnf.io.checkpoint_digest import (
    DIGEST_KEY,
    HEADER_KEY,
    check_digest,
    content_digest,
)
from regnf.observations.rgbd_samples import CaptureLike, capture_where
from regnf.observations.visibility import (
    DEFAULT_MARGIN,
    DEFAULT_RESOLUTION,
    VisibilityGrid,
    build_visibility,
)

FORMAT_VERSION = 2
"""Written by :func:`save_field`. 2: the header records :data:`DIGEST_KEY`."""

LEGACY_FORMAT_VERSIONS = (1,)
"""Older versions: refused with what to do (see the module docstring)."""

CONVERT_V1 = "scripts/convert_checkpoint_v1.py"
"""The repository's converter of version-1 files, named in the refusal."""

VISIBILITY_KEY = "visibility"
"""Header key of the visibility grid's metadata (:meth:`VisibilityGrid.to_json`), or null."""

VISIBILITY_TENSOR = "visibility.counts"
"""Name of the visibility grid's counts, (R_x, R_y, R_z) uint8, when the header has a grid."""

STORED_TWICE = {"bounds": "bounds", "to_world": "to_world"}
"""Header keys that the weights also hold as a buffer (header key -> tensor name). A reader of
the header alone (a stage) and the loaded field must see the same numbers, so the two copies
must be equal (compared in float64, which holds both exactly)."""

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


def _read(path: Path, limits: ArchitectureLimits | None) -> tuple[dict, _Parsed]:
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
    _check_version(path, header.get("format_version"))
    arch = header.get("architecture")
    if arch != ARCHITECTURE:
        raise CheckpointError(path, f"unknown architecture {arch!r} (expected {ARCHITECTURE!r})")
    for key in ("config", "bounds", "to_world"):
        if key not in header:
            raise CheckpointError(path, f"the header lacks '{key}'")
    header_contents = _parse(path, header, limits)
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


def _check_version(path: Path, version: object) -> None:
    if version == FORMAT_VERSION:
        return
    if version in LEGACY_FORMAT_VERSIONS:
        raise CheckpointError(
            path,
            f"format version {version} has no content digest and is no longer trusted; retrain the "
            f"field (cached fields are remade) or convert it: python {CONVERT_V1} FILE "
            "(in the regnf repository)",
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


def read_header(path: str | os.PathLike, limits: ArchitectureLimits | None = None) -> dict:
    """Read and validate the JSON header of a checkpoint without loading weights.

    Cheap (reads the safetensors header only) and safe on hostile files: the architecture is
    bounded by ``limits`` before anything could build it.

    Parameters
    ----------
    path : str or PathLike
    limits : ArchitectureLimits, optional
        The largest architecture accepted (default: the MAX_* constants).

    Returns
    -------
    dict
        The header as stored, :data:`DIGEST_KEY` included.

    Raises
    ------
    CheckpointError
        Missing or unreadable file, no or corrupted header, an unsupported or legacy format
        version, unknown architecture, a config of the
        wrong types or beyond ``limits``, bounds with min >= max, a ``to_world`` that is not
        a similarity, badly typed label / name / symmetry / provenance, a malformed digest,
        a ``visibility`` block of the wrong types or beyond ``limits``.
        The digest itself is compared by :func:`verify_checkpoint` and :func:`load_field`.
    """
    return _read(Path(path), limits)[0]


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
    header, parsed = _read(path, limits)
    check_digest(path, header)
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
) -> NeuralSDF:
    """Load a checkpoint written by :func:`save_field`, validating every tensor.

    Parameters
    ----------
    path : str or PathLike
    device : torch.device or str
        Where the field is moved after loading.
    limits : ArchitectureLimits, optional
        The largest architecture accepted (default: the MAX_* constants).

    Raises
    ------
    CheckpointError
        Any of :func:`read_header`'s; missing / unexpected tensors, wrong shapes or dtypes, a
        content digest mismatch, non-finite weights, a buffer that disagrees with its header
        copy (``to_world``, ``bounds``). The field's ``visibility`` is the stored grid, or None
        when the header has none.
    """
    path = Path(path)
    header, parsed = _read(path, limits)
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
            check_digest(path, header)
            state = {}
            for name, (_, dtype) in expected.items():
                t = f.get_tensor(name)
                if t.dtype != dtype:
                    raise CheckpointError(path, f"tensor '{name}' has dtype {t.dtype}, expected {dtype}")
                if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                    raise CheckpointError(path, f"tensor '{name}' has non-finite values")
                state[name] = in_fresh_memory(t)  # its alignment not the header's length (core.fresh_memory)
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
    (:func:`regnf.observations.visibility.build_visibility`), as
    :func:`regnf.training.training.train_rgbd` builds it, and replaces any grid the checkpoint
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
        As for :func:`regnf.observations.visibility.build_visibility` (defaults: training's).
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
