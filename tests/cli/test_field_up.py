"""One ``--up`` for ``regnf discover`` and ``regnf register``: given, recorded by training, or +Z."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from regnf.cli.commands_discover import Discover
from regnf.cli.field_up import field_frame_up, scene_up, with_scene_up
from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDF
from regnf.registration.candidates import CandidateConfig
from regnf.registration.discovery import DiscoveryConfig
from regnf.registration.pipeline import RegistrationConfig
from tests.scene_graph.helpers import TINY, similarity


def scene_field(provenance: dict, to_world: np.ndarray | None = None) -> NeuralSDF:
    M = torch.eye(4, dtype=torch.float64) if to_world is None else torch.as_tensor(to_world)
    return NeuralSDF(TINY, to_world=M, info=FieldInfo(label="scene", name="room", provenance=provenance))


def test_auto_takes_the_up_training_recorded_else_plus_z() -> None:
    up = scene_up(scene_field({"up": [0.0, 0.6, 0.8]}), "auto")
    assert up.metres.tolist() == [0.0, 0.6, 0.8] and up.line == "up: (0.00, 0.60, 0.80) (from the scene field's training)"
    up = scene_up(scene_field({}), "auto")
    assert up.metres.tolist() == [0.0, 0.0, 1.0] and up.line == "up: +Z (the scene field records no up; regnf's default)"


def test_a_given_up_wins_over_the_recorded_one() -> None:
    up = scene_up(scene_field({"up": [0.0, 0.6, 0.8]}), "-y")
    assert up.metres.tolist() == [0.0, -1.0, 0.0] and up.line == "up: -Y (given by --up)"


def test_a_recorded_up_that_is_no_direction_is_refused() -> None:
    with pytest.raises(ValueError, match="provenance 'up' must be 3 finite numbers"):
        scene_up(scene_field({"up": [0.0, 0.0]}), "auto")


def test_the_registration_takes_the_up_in_the_field_frame() -> None:
    M = similarity(0.0, (1.0, 2.0, 3.0), 2.5, tilt=0.3)  # field -> metres: scale, tilt about x
    field = scene_field({}, M)
    R = M[:3, :3] / 2.5
    up = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(field_frame_up(field, up), R.T @ up, atol=1e-12)
    config = with_scene_up(RegistrationConfig(), field, up)
    np.testing.assert_allclose(config.scene_sampling.up, R.T @ up, atol=1e-12)


def test_discover_sets_both_ups_from_one_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    field = scene_field({"up": [0.0, -1.0, 0.0]})
    command = Discover(scene=tmp_path / "s.safetensors", library=(), out=tmp_path / "out")
    config = command.scene_up_config(field)
    assert config.candidates.up == (0.0, -1.0, 0.0) and config.registration.scene_sampling.up == (0.0, -1.0, 0.0)
    assert "up: -Y (from the scene field's training)" in capsys.readouterr().err
    given = dataclasses.replace(command, up="+x").scene_up_config(field)
    assert given.candidates.up == (1.0, 0.0, 0.0) and given.registration.scene_sampling.up == (1.0, 0.0, 0.0)
    # The nested options, set by hand, are kept under --up auto.
    nested = DiscoveryConfig(candidates=CandidateConfig(up=(0.0, 1.0, 0.0)))
    kept = dataclasses.replace(command, discovery=nested).scene_up_config(field)
    assert kept.candidates.up == (0.0, 1.0, 0.0) and kept.registration.scene_sampling.up == (0.0, 0.0, 1.0)
    assert "up: as given by --discovery.candidates.up" in capsys.readouterr().err
