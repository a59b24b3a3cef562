"""Hostile checkpoints: contents that disagree with the header, flipped bits, forged sizes,
old formats. Every refusal is a one-line CheckpointError naming the file and the problem."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDF, NeuralSDFConfig
from regnf.io.checkpoint import (
    DIGEST_KEY,
    FORMAT_VERSION,
    HEADER_KEY,
    ArchitectureLimits,
    CheckpointError,
    content_digest,
    load_field,
    read_header,
    save_field,
    verify_checkpoint,
)
from regnf.io.checkpoint_checks import MAX_LEVELS
from regnf.io.checkpoint_digest import checkpoint_digest

TINY = NeuralSDFConfig(levels=2, finest_resolution=16, hidden_dim=16, base_resolution=8,
                       geo_feature_dim=3, color_hidden_dim=8)
"""As tests/scene_graph/helpers.py: a field of a few thousand values."""


def saved(tmp_path: Path, name: str = "f.safetensors") -> Path:
    """A tiny field 0.6 m across, standing at (1, 2, 0.3) m, saved with save_field."""
    torch.manual_seed(0)
    to_world = torch.eye(4, dtype=torch.float64)
    to_world[:3, :3] *= 0.6
    to_world[:3, 3] = torch.tensor([1.0, 2.0, 0.3], dtype=torch.float64)
    field = NeuralSDF(TINY, to_world=to_world, info=FieldInfo(label="chair", name="c"))
    return save_field(field, tmp_path / name)


def stored(path: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    """The header and tensors of a checkpoint, as stored."""
    with safe_open(str(path), framework="pt") as f:
        header = json.loads(f.metadata()[HEADER_KEY])
    return header, load_file(str(path))


def rewrite(
    path: Path,
    edit_tensors: Callable[[dict[str, torch.Tensor]], None] | None = None,
    edit_header: Callable[[dict], None] | None = None,
    redigest: bool = True,
) -> Path:
    """Edit a checkpoint in place; ``redigest`` recomputes the digest as a forger can."""
    header, tensors = stored(path)
    if edit_tensors:
        edit_tensors(tensors)
    if edit_header:
        edit_header(header)
    if redigest and DIGEST_KEY in header:
        header[DIGEST_KEY] = content_digest(header, tensors)
    save_file(tensors, str(path), metadata={HEADER_KEY: json.dumps(header)})
    return path


def refused(fn: Callable[[Path], object], path: Path, match: str) -> str:
    """The one-line message of the CheckpointError ``fn(path)`` raises; it names the file."""
    with pytest.raises(CheckpointError, match=match) as info:
        fn(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message
    assert info.value.path == path
    return message


# -- quantities stored twice: the header and the buffers ---------------------------------------
def _zero_to_world(t: dict[str, torch.Tensor]) -> None:
    t["to_world"].zero_()


def _move_to_world_5m(t: dict[str, torch.Tensor]) -> None:
    t["to_world"][0, 3] += 5.0


def _grow_bounds(t: dict[str, torch.Tensor]) -> None:
    t["bounds"][1, 2] = 1.5


@pytest.mark.parametrize(
    ("edit", "name"),
    [(_zero_to_world, "to_world"), (_move_to_world_5m, "to_world"), (_grow_bounds, "bounds")],
    ids=["to_world-zeroed", "to_world-moved-5m", "bounds-grown"],
)
def test_a_buffer_that_disagrees_with_the_header_is_refused(tmp_path: Path, edit, name: str) -> None:
    # The digest is recomputed (it is no signature), so only the consistency check can see it.
    path = rewrite(saved(tmp_path), edit)
    match = f"tensor '{name}' disagrees with the header's '{name}'"
    refused(load_field, path, match)
    refused(verify_checkpoint, path, match)
    read_header(path)  # the header alone is fine: it is the weights that were edited


def test_an_edited_buffer_without_a_new_digest_fails_the_digest(tmp_path: Path) -> None:
    path = rewrite(saved(tmp_path), _move_to_world_5m, redigest=False)
    refused(load_field, path, "content digest mismatch")
    refused(verify_checkpoint, path, "content digest mismatch")


def _flip_last_byte(path: Path) -> None:
    """Edit the file in place (same inode, same size): its last tensor byte inverted."""
    with open(path, "r+b") as f:
        f.seek(-1, os.SEEK_END)
        b = f.read(1)
        f.seek(-1, os.SEEK_END)
        f.write(bytes([b[0] ^ 0xFF]))


def test_a_file_edited_in_place_right_after_its_check_is_refused(tmp_path: Path) -> None:
    # Freshly written: never remembered as checked, however fast the edit follows.
    path = saved(tmp_path)
    verify_checkpoint(path)
    _flip_last_byte(path)
    refused(verify_checkpoint, path, "content digest mismatch")
    refused(load_field, path, "content digest mismatch")


def test_a_stable_file_is_hashed_once_until_it_changes(tmp_path: Path, monkeypatch) -> None:
    import regnf.io.checkpoint_digest as digests

    monkeypatch.setattr(digests, "STABLE_SECONDS", 0.0)  # as if the file were older
    path = saved(tmp_path)
    hashed: list[Path] = []
    real = digests.checkpoint_digest
    monkeypatch.setattr(digests, "checkpoint_digest", lambda p: hashed.append(p) or real(p))
    verify_checkpoint(path)
    load_field(path)
    verify_checkpoint(path)
    assert hashed == [path]  # checked once, then known by its identity
    # A replacing write (a new file renamed over it, as every regnf writer does) is hashed again.
    edited = rewrite(saved(tmp_path, "g.safetensors"), _move_to_world_5m, redigest=False)
    os.replace(edited, path)
    refused(verify_checkpoint, path, "content digest mismatch")
    assert len(hashed) == 2


@pytest.mark.parametrize(
    ("to_world", "match"),
    [
        ([[0.0] * 4] * 3 + [[0.0, 0.0, 0.0, 1.0]], "determinant 0"),
        ([[-1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]], "reflection"),
        ([[1.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]], "non-uniform"),
        ([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0.5, 1.0]], "last row"),
    ],
    ids=["singular", "mirror", "non-uniform", "projective"],
)
def test_a_header_to_world_that_is_no_similarity_is_refused(tmp_path: Path, to_world, match: str) -> None:
    def edit(t: dict[str, torch.Tensor]) -> None:
        t["to_world"] = torch.tensor(to_world, dtype=torch.float64)

    def edit_header(h: dict) -> None:
        h["to_world"] = to_world

    path = rewrite(saved(tmp_path), edit, edit_header)  # both copies agree: the value is bad
    for fn in (read_header, load_field, verify_checkpoint):
        refused(fn, path, f"'to_world' is not a similarity.*{match}")


def test_header_bounds_must_have_min_below_max(tmp_path: Path) -> None:
    def flat(h: dict) -> None:
        h["bounds"][1][0] = h["bounds"][0][0]

    path = rewrite(saved(tmp_path), edit_header=flat)
    refused(read_header, path, "'bounds' must have min < max")


# -- flipped bits --------------------------------------------------------------------------------
def _flip_low_bit(path: Path, tensor: str) -> None:
    """Flip the lowest mantissa bit of the first float32 of ``tensor`` in the file's bytes."""
    data = bytearray(path.read_bytes())
    n = int.from_bytes(data[:8], "little")
    start = json.loads(data[8 : 8 + n])[tensor]["data_offsets"][0]
    data[8 + n + start] ^= 1  # little-endian: the first byte holds the lowest mantissa bits
    path.write_bytes(bytes(data))


def test_a_flipped_bit_that_stays_finite_is_refused(tmp_path: Path) -> None:
    path = saved(tmp_path)
    before = stored(path)[1]["sdf_layers.0.weight"].clone()
    _flip_low_bit(path, "sdf_layers.0.weight")
    after = stored(path)[1]["sdf_layers.0.weight"]
    assert torch.isfinite(after).all() and not torch.equal(after, before)  # a plausible weight
    refused(load_field, path, "content digest mismatch")
    refused(verify_checkpoint, path, "content digest mismatch")


def test_a_flipped_bit_in_the_header_is_refused(tmp_path: Path) -> None:
    def rename(h: dict) -> None:
        h["label"] = "table"

    path = rewrite(saved(tmp_path), edit_header=rename, redigest=False)
    refused(load_field, path, "content digest mismatch")


def test_the_digest_of_the_file_is_the_one_in_its_header(tmp_path: Path) -> None:
    path = saved(tmp_path)
    header, tensors = stored(path)
    assert header["format_version"] == FORMAT_VERSION == 2
    assert header[DIGEST_KEY] == checkpoint_digest(path) == content_digest(header, tensors)
    assert verify_checkpoint(path) == read_header(path) == header


@pytest.mark.parametrize("digest", [None, "0" * 63, "g" * 64, 12])
def test_a_malformed_digest_is_refused_by_the_header_reader(tmp_path: Path, digest) -> None:
    def edit(h: dict) -> None:
        if digest is None:
            del h[DIGEST_KEY]
        else:
            h[DIGEST_KEY] = digest

    path = rewrite(saved(tmp_path), edit_header=edit, redigest=False)
    refused(read_header, path, f"'{DIGEST_KEY}' must be 64 hex digits")


# -- forged sizes: refused from the header, before anything is built ---------------------------
@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"levels": 10**8}, r"levels = 100000000 exceeds the limit 32"),
        ({"hidden_layers": 3e6}, r"'hidden_layers' must be an integer, got 3000000.0"),
        ({"hidden_layers": 3_000_000}, r"hidden_layers = 3000000 exceeds the limit 64"),
        ({"finest_resolution": 4096, "base_resolution": 2048}, r"parameters exceed the limit"),
        ({"hidden_dim": 10**6}, r"hidden_dim = 1000000 exceeds"),
    ],
    ids=["levels-1e8", "hidden_layers-3e6-float", "hidden_layers-3e6", "huge-grid", "wide"],
)
def test_a_huge_architecture_is_refused_in_well_under_a_second(tmp_path: Path, change: dict, match: str) -> None:
    def edit(h: dict) -> None:
        h["config"].update(change)

    path = rewrite(saved(tmp_path), edit_header=edit)
    for fn in (read_header, load_field, verify_checkpoint):
        start = time.perf_counter()
        refused(fn, path, match)
        assert time.perf_counter() - start < 0.5, fn.__name__


def test_limits_are_a_parameter(tmp_path: Path) -> None:
    path = saved(tmp_path)  # TINY: 2 levels
    strict = ArchitectureLimits(max_levels=1)
    refused(lambda p: read_header(p, limits=strict), path, r"levels = 2 exceeds the limit 1 \(ArchitectureLimits.max_levels\)")
    refused(lambda p: load_field(p, limits=strict), path, "max_levels")

    def deep(h: dict) -> None:
        h["config"]["levels"] = MAX_LEVELS + 1

    rewrite(path, edit_header=deep)
    refused(read_header, path, "exceeds the limit")
    # Beyond the default limit, allowed by the caller: the header passes; the weights (for 2
    # levels) then do not match the architecture.
    assert read_header(path, limits=ArchitectureLimits(max_levels=MAX_LEVELS + 1))["config"]["levels"] == 33
    refused(lambda p: load_field(p, limits=ArchitectureLimits(max_levels=MAX_LEVELS + 1)), path, "missing tensors")


# -- format versions ---------------------------------------------------------------------------
def _as_version_1(h: dict) -> None:
    h["format_version"] = 1
    del h[DIGEST_KEY]


CONVERT_V1 = Path(__file__).resolve().parents[2] / "scripts" / "convert_checkpoint_v1.py"


def _convert(*args: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(CONVERT_V1), *map(str, args)], capture_output=True, text=True,
                          check=False, timeout=300)


def test_version_1_is_refused_with_what_to_do_and_the_script_converts_it(tmp_path: Path) -> None:
    path = rewrite(saved(tmp_path), edit_header=_as_version_1)
    for fn in (read_header, load_field, verify_checkpoint):
        message = refused(fn, path, "format version 1 has no content digest")
        assert "retrain" in message and "scripts/convert_checkpoint_v1.py" in message
    out = tmp_path / "converted.safetensors"
    done = _convert(path, out)
    assert done.returncode == 0, done.stderr
    assert verify_checkpoint(out)["format_version"] == FORMAT_VERSION
    assert torch.equal(load_field(out).to_world, stored(path)[1]["to_world"])
    assert _convert(out).returncode == 1  # a version-2 file: nothing to convert


def test_the_converter_still_checks_everything_else(tmp_path: Path) -> None:
    path = rewrite(saved(tmp_path), _move_to_world_5m, _as_version_1)
    done = _convert(path, tmp_path / "converted.safetensors")
    assert done.returncode == 1 and "tensor 'to_world' disagrees" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "converted.safetensors").exists()


@pytest.mark.parametrize("version", [3, None, "2"])
def test_other_versions_are_refused(tmp_path: Path, version) -> None:
    def edit(h: dict) -> None:
        h["format_version"] = version

    path = rewrite(saved(tmp_path), edit_header=edit)
    refused(read_header, path, f"unsupported format version {version!r}")


# -- file mode ------------------------------------------------------------------------------------
@pytest.mark.parametrize("umask", [0o022, 0o027, 0o002])
def test_a_saved_checkpoint_has_the_users_umask(tmp_path: Path, umask: int) -> None:
    old = os.umask(umask)
    try:
        path = saved(tmp_path)
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.safetensors"]


def test_a_field_that_could_not_be_read_back_is_not_saved(tmp_path: Path) -> None:
    to_world = torch.diag(torch.tensor([1.0, 2.0, 1.0, 1.0], dtype=torch.float64))
    field = NeuralSDF(TINY, to_world=to_world)
    path = tmp_path / "f.safetensors"
    with pytest.raises(CheckpointError, match="'to_world' is not a similarity.*non-uniform"):
        save_field(field, path)
    assert not path.exists()
