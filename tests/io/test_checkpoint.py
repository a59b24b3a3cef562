"""Checkpoints: bit-exact round trips, and a clear CheckpointError naming the file for every
kind of bad file (forged with ``safetensors.torch.save_file``)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from regnf.core import atomic_io
from regnf.fields.field import FieldInfo, Symmetry
from regnf.fields.neural_sdf import ARCHITECTURE, NeuralSDF, NeuralSDFConfig, parameter_count
from regnf.io.checkpoint import (
    DIGEST_KEY,
    HEADER_KEY,
    CheckpointError,
    content_digest,
    field_header,
    load_field,
    read_header,
    save_field,
)

TINY = NeuralSDFConfig(
    levels=3,
    features_per_level=2,
    base_resolution=8,
    finest_resolution=16,
    hidden_dim=16,
    geo_feature_dim=7,
    color_hidden_dim=16,
)


def make_field(config: NeuralSDFConfig = TINY, seed: int = 0) -> NeuralSDF:
    """A field with every parameter randomised (not just its initialisation) and rich metadata."""
    torch.manual_seed(seed)
    angle = 0.7
    to_world = torch.tensor(
        [
            [1.7 * math.cos(angle), -1.7 * math.sin(angle), 0.0, 1.0 / 3.0],
            [1.7 * math.sin(angle), 1.7 * math.cos(angle), 0.0, -2.5],
            [0.0, 0.0, 1.7, 0.1],
            [0.0, 0.0, 0.0, 1.0],
        ],
        dtype=torch.float64,
    )
    info = FieldInfo(
        label="chair",
        name="dc",
        symmetry=Symmetry(4),
        provenance={"trained_from": "rgbd", "steps": 12, "nested": {"a": [1, 2.5, None]}},
    )
    bounds = torch.tensor([[-0.9, -0.5, -0.3], [0.8, 0.6, 0.95]])
    field = NeuralSDF(config, bounds=bounds, to_world=to_world, info=info)
    with torch.no_grad():
        for p in field.parameters():
            p.normal_(0.0, 0.3)
    return field.eval()


def query_points(n: int = 512) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    lo, hi = torch.tensor([-0.9, -0.5, -0.3]), torch.tensor([0.8, 0.6, 0.95])
    return lo + torch.rand(n, 3, generator=g) * (hi - lo)


def tensors_of(field: NeuralSDF) -> dict[str, torch.Tensor]:
    return {k: v.detach().contiguous().clone() for k, v in field.state_dict().items()}


def forge(path: Path, tensors: dict[str, torch.Tensor], header: dict | str | None) -> Path:
    """Write a checkpoint by hand. A dict header gets a correct content digest (as a forger
    can compute one), so that the check each test aims at is reached, not the digest's."""
    if isinstance(header, dict):
        header = {**header, DIGEST_KEY: content_digest(header, tensors)}
    meta = (
        None
        if header is None
        else {HEADER_KEY: header if isinstance(header, str) else json.dumps(header)}
    )
    save_file(tensors, str(path), metadata=meta)
    return path


def assert_checkpoint_error(path: Path, match: str) -> CheckpointError:
    with pytest.raises(CheckpointError, match=match) as info:
        load_field(path)
    assert str(path) in str(info.value)
    assert info.value.path == path
    return info.value


# -- round trip ---------------------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ["dense", "hash"])
def test_round_trip_is_bit_identical(tmp_path: Path, encoding: str) -> None:
    config = NeuralSDFConfig(**{**TINY.to_json(), "encoding": encoding, "hash_table_size_log2": 9})
    field = make_field(config)
    path = save_field(field, tmp_path / "f.safetensors")
    assert path == tmp_path / "f.safetensors" and path.is_file()
    assert sorted(os.listdir(tmp_path)) == ["f.safetensors"]  # no temporary file left over
    loaded = load_field(path)
    assert isinstance(loaded, NeuralSDF) and loaded.config == config
    x = query_points()
    with torch.no_grad():
        assert torch.equal(loaded.sdf(x), field.sdf(x))
    assert torch.equal(loaded.color(x), field.color(x))
    assert field.sdf(x).std() > 0.01  # the comparison is not between two constants
    a, b = field.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) and a[k].dtype == b[k].dtype for k in a)
    # Metadata, exactly: float64 to_world survives JSON without rounding.
    assert loaded.to_world.dtype == torch.float64
    assert torch.equal(loaded.to_world, field.to_world)
    assert torch.equal(loaded.bounds, field.bounds)
    assert loaded.label == "chair" and loaded.name == "dc"
    assert loaded.symmetry == Symmetry(4)
    assert loaded.info.provenance == {
        "trained_from": "rgbd",
        "steps": 12,
        "nested": {"a": [1, 2.5, None]},
    }
    header = read_header(path)
    # Format 2: the stored header is field_header plus the content digest.
    assert header == {**json.loads(json.dumps(field_header(field))), DIGEST_KEY: header[DIGEST_KEY]}
    assert header["architecture"] == ARCHITECTURE
    assert header["config"]["encoding"] == encoding


def test_save_overwrites_and_accepts_str_paths(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "f.safetensors"
    save_field(make_field(seed=0), str(path))
    save_field(make_field(seed=1), path)
    x = query_points(64)
    with torch.no_grad():
        assert torch.equal(load_field(path).sdf(x), make_field(seed=1).sdf(x))
    assert sorted(os.listdir(path.parent)) == ["f.safetensors"]


# -- files that are not checkpoints -------------------------------------------------------------
def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.safetensors"
    assert_checkpoint_error(path, "does not exist")
    with pytest.raises(CheckpointError, match="does not exist") as info:
        read_header(path)
    assert str(path) in str(info.value)


def test_directory(tmp_path: Path) -> None:
    path = tmp_path / "dir.safetensors"
    path.mkdir()
    assert_checkpoint_error(path, "not a file")


def test_truncated_file(tmp_path: Path) -> None:
    path = save_field(make_field(), tmp_path / "f.safetensors")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    assert_checkpoint_error(path, "not a readable safetensors file|truncated")


def test_truncated_inside_the_header(tmp_path: Path) -> None:
    path = save_field(make_field(), tmp_path / "f.safetensors")
    path.write_bytes(path.read_bytes()[:100])
    assert_checkpoint_error(path, "not a readable safetensors file")


def test_garbage_bytes(tmp_path: Path) -> None:
    path = tmp_path / "g.safetensors"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    assert_checkpoint_error(path, "not a readable safetensors file")


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "e.safetensors"
    path.write_bytes(b"")
    assert_checkpoint_error(path, "not a readable safetensors file")


def test_safetensors_without_regnf_header(tmp_path: Path) -> None:
    path = forge(tmp_path / "plain.safetensors", tensors_of(make_field()), None)
    assert_checkpoint_error(path, "no 'regnf' JSON header")
    other = forge(tmp_path / "other.safetensors", {"w": torch.zeros(3)}, None)
    save_file({"w": torch.zeros(3)}, str(other), metadata={"format": "pt"})
    assert_checkpoint_error(other, "no 'regnf' JSON header")


# -- bad headers ----------------------------------------------------------------------------------
def test_unknown_architecture(tmp_path: Path) -> None:
    field = make_field()
    header = {**field_header(field), "architecture": "someone.else.v9"}
    path = forge(tmp_path / "a.safetensors", tensors_of(field), header)
    assert_checkpoint_error(path, "unknown architecture 'someone.else.v9'")
    del header["architecture"]
    path = forge(tmp_path / "b.safetensors", tensors_of(field), header)
    assert_checkpoint_error(path, "unknown architecture None")


def test_corrupted_json_header(tmp_path: Path) -> None:
    field = make_field()
    text = json.dumps(field_header(field))
    path = forge(tmp_path / "j.safetensors", tensors_of(field), text[: len(text) // 2])
    assert_checkpoint_error(path, "JSON header is corrupted")
    path = forge(tmp_path / "k.safetensors", tensors_of(field), "[1, 2, 3]")
    assert_checkpoint_error(path, "not an object")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            {"config": {**TINY.to_json(), "depth_of_field": 3}},
            "bad architecture config.*depth_of_field",
        ),
        ({"config": {**TINY.to_json(), "encoding": "fourier"}}, "bad architecture config.*fourier"),
        ({"bounds": [[0.0, 0.0, 0.0]]}, "'bounds' has shape"),
        ({"bounds": [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]}, "'bounds' must have min < max"),
        ({"to_world": [[1.0, 0.0], [0.0, 1.0]]}, "'to_world' has shape"),
        ({"to_world": [[float("nan")] * 4] * 4}, "'to_world' has non-finite"),
        ({"bounds": "everywhere"}, "'bounds' is not a numeric matrix"),
        ({"symmetry": {"axis": "x", "order": 2}}, "bad header.*axis"),
    ],
)
def test_bad_header_fields(tmp_path: Path, change: dict, match: str) -> None:
    field = make_field()
    path = forge(tmp_path / "h.safetensors", tensors_of(field), {**field_header(field), **change})
    assert_checkpoint_error(path, match)


def test_header_without_config(tmp_path: Path) -> None:
    field = make_field()
    header = field_header(field)
    del header["config"]
    path = forge(tmp_path / "c.safetensors", tensors_of(field), header)
    assert_checkpoint_error(path, "lacks 'config'")


# -- bad tensors ----------------------------------------------------------------------------------
def test_tensor_with_the_wrong_shape(tmp_path: Path) -> None:
    """Weights of a wider network under the header of the declared one."""
    declared = make_field()
    wider = make_field(NeuralSDFConfig(**{**TINY.to_json(), "hidden_dim": 24}))
    assert tensors_of(declared).keys() == tensors_of(wider).keys()
    path = forge(tmp_path / "s.safetensors", tensors_of(wider), field_header(declared))
    assert_checkpoint_error(path, r"tensor '.*' has shape \(24, .*expected \(16, ")


def test_missing_tensor(tmp_path: Path) -> None:
    field = make_field()
    tensors = tensors_of(field)
    del tensors["color_net.2.bias"]
    path = forge(tmp_path / "m.safetensors", tensors, field_header(field))
    assert_checkpoint_error(path, r"missing tensors \['color_net.2.bias'\]")


def test_extra_tensor(tmp_path: Path) -> None:
    field = make_field()
    tensors = {**tensors_of(field), "backdoor.weight": torch.zeros(2, 2)}
    path = forge(tmp_path / "x.safetensors", tensors, field_header(field))
    assert_checkpoint_error(path, r"unexpected tensors \['backdoor.weight'\]")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_weights(tmp_path: Path, bad: float) -> None:
    field = make_field()
    tensors = tensors_of(field)
    tensors["sdf_layers.1.weight"][3, 2] = bad
    path = forge(tmp_path / "n.safetensors", tensors, field_header(field))
    assert_checkpoint_error(path, "tensor 'sdf_layers.1.weight' has non-finite values")


def test_wrong_dtype(tmp_path: Path) -> None:
    field = make_field()
    tensors = tensors_of(field)
    tensors["sdf_layers.0.bias"] = tensors["sdf_layers.0.bias"].double()
    path = forge(tmp_path / "d.safetensors", tensors, field_header(field))
    assert_checkpoint_error(path, "tensor 'sdf_layers.0.bias' has dtype torch.float64")


# -- saving ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["f.pt", "f.safetensor", "f", "f.safetensors.bak"])
def test_wrong_suffix_on_save(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    with pytest.raises(CheckpointError, match=r"\.safetensors") as info:
        save_field(make_field(), path)
    assert str(path) in str(info.value)
    assert not path.exists() and os.listdir(tmp_path) == []


def test_failed_save_leaves_the_old_checkpoint_intact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = save_field(make_field(seed=0), tmp_path / "f.safetensors")
    before = path.read_bytes()

    def disk_full(fd: int) -> None:  # the bytes were written to the temporary, then the flush fails
        raise OSError("disk full")

    monkeypatch.setattr(atomic_io.os, "fsync", disk_full)
    with pytest.raises(OSError, match="disk full"):
        save_field(make_field(seed=1), path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["f.safetensors"]  # the temporary file is gone
    monkeypatch.undo()
    x = query_points(64)
    with torch.no_grad():
        assert torch.equal(load_field(path).sdf(x), make_field(seed=0).sdf(x))


def test_failed_first_save_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(fd: int) -> None:
        raise KeyboardInterrupt  # even an interrupt must not leave a partial file

    monkeypatch.setattr(atomic_io.os, "fsync", fail)
    with pytest.raises(KeyboardInterrupt):
        save_field(make_field(), tmp_path / "new.safetensors")
    assert os.listdir(tmp_path) == []


# -- malformed header VALUES are reported as CheckpointError naming the file ----------------
@pytest.mark.parametrize(
    "change",
    [
        {"provenance": [1, 2]},
        {"provenance": "abc"},
        {"symmetry": [4]},
        {"config": {**TINY.to_json(), "levels": "3"}},
        {"config": {**TINY.to_json(), "hidden_dim": 16.5}},
    ],
    ids=["provenance-list", "provenance-str", "symmetry-list", "levels-str", "hidden-float"],
)
def test_wrongly_typed_header_values(tmp_path: Path, change: dict) -> None:
    field = make_field()
    path = forge(tmp_path / "t.safetensors", tensors_of(field), {**field_header(field), **change})
    assert_checkpoint_error(path, r".")


def test_forged_huge_grid_is_refused_before_allocating(tmp_path: Path) -> None:
    # A header asking for a 4096^3 grid would need terabytes; its parameter count is over the
    # limit, so it is refused from the header alone (format 2), before any skeleton is built.
    field = make_field()
    huge = {**TINY.to_json(), "levels": 2, "base_resolution": 2048, "finest_resolution": 4096}
    path = forge(tmp_path / "huge.safetensors", tensors_of(field), {**field_header(field), "config": huge})
    with pytest.raises(CheckpointError, match="architecture refused: .* parameters exceed") as err:
        load_field(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    "change",
    [{}, {"encoding": "hash", "hash_table_size_log2": 9}, {"view_dependent": True, "hidden_layers": 0},
     {"levels": 1, "finest_resolution": 8}, {"color_grid_features": True}],
    ids=["dense", "hash", "view-dependent-no-hidden", "one-level", "colour-from-grids"],
)
def test_parameter_count_is_exact_without_building(change: dict) -> None:
    # The architecture limit is checked on this count, before any model exists.
    config = NeuralSDFConfig(**{**TINY.to_json(), **change})
    bounds = torch.tensor([[-0.9, -0.5, -0.3], [0.8, 0.6, 0.95]])
    model = NeuralSDF(config, bounds=bounds)
    assert parameter_count(config, bounds[1] - bounds[0]) == sum(p.numel() for p in model.parameters())


def test_loaded_weights_sit_in_aligned_memory_whatever_the_header_length(tmp_path: Path) -> None:
    # The same weights under headers of 8 different lengths: a tensor read in place would lie at
    # an address that moves with the header, and vector kernels may round differently there.
    field = make_field()
    for pad in range(8):
        field.info.provenance = {"note": "x" * pad}
        back = load_field(save_field(field, tmp_path / f"f{pad}.safetensors"))
        for name, t in [*back.named_parameters(), *back.named_buffers()]:
            assert t.data_ptr() % 64 == 0, (pad, name)
            assert torch.equal(t, dict([*field.named_parameters(), *field.named_buffers()])[name])
