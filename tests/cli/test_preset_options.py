"""Options made from a config class: one per setting, unset keeps the preset's value."""

from __future__ import annotations

import dataclasses

import pytest
import tyro

from regnf.cli.commands_fields import DISTILLATION_OPTIONS, TRAINING_OPTIONS
from regnf.cli.preset_options import preset_options, with_options
from regnf.core.errors import RegnfError
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.training.distill import DistillConfig
from regnf.training.presets import OBJECT_MESH, OBJECT_RGBD, SCENE_RGBD
from regnf.training.training import RGBDTrainConfig


def leaves(config_type: type, prefix: str = "") -> set[str]:
    """Dotted names of every non-dataclass field of ``config_type``, nested configs included."""
    out: set[str] = set()
    for f in dataclasses.fields(config_type):
        value = getattr(config_type(), f.name)
        if dataclasses.is_dataclass(value):
            out |= leaves(type(value), f"{prefix}{f.name}.")
        else:
            out.add(prefix + f.name)
    return out


def test_every_setting_but_the_commands_own_is_an_option() -> None:
    assert leaves(TRAINING_OPTIONS) == leaves(RGBDTrainConfig) - {"seed", "device", "pose_refine.mode"}
    assert leaves(DISTILLATION_OPTIONS) == leaves(DistillConfig) - {"device", "up", "scale"}
    assert "architecture.finest_resolution" in leaves(TRAINING_OPTIONS)


@pytest.mark.parametrize("preset", [OBJECT_RGBD, SCENE_RGBD])
def test_options_left_unset_keep_the_preset(preset: RGBDTrainConfig) -> None:
    assert with_options(preset, TRAINING_OPTIONS()) == preset
    assert with_options(OBJECT_MESH, DISTILLATION_OPTIONS()) == OBJECT_MESH


def test_an_option_given_changes_that_setting_only() -> None:
    args = ["--training.steps", "7", "--training.architecture.levels", "3", "--training.near-band-m", "0.01", "0.03"]
    options = tyro.cli(TRAINING_OPTIONS, args=[a.replace("--training.", "--") for a in args])
    got = with_options(SCENE_RGBD, options)
    want = dataclasses.replace(SCENE_RGBD, steps=7, near_band_m=(0.01, 0.03),
                               architecture=dataclasses.replace(SCENE_RGBD.architecture, levels=3))
    assert got == want
    assert got.architecture.finest_resolution == 256 and SCENE_RGBD.steps == 400  # the preset is not changed


def test_a_bad_value_is_refused_by_the_config() -> None:
    options = tyro.cli(TRAINING_OPTIONS, args=["--w-edge", "-1"])
    with pytest.raises(RegnfError, match="RGBDTrainConfig.w_edge must be a finite number >= 0"):
        with_options(OBJECT_RGBD, options)


def test_the_help_shows_each_presets_value(capsys: pytest.CaptureFixture[str]) -> None:
    from regnf.cli.app import main

    with pytest.raises(SystemExit):
        main(["train", "--help-all"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())
    assert "--training.w-edge" in text and "(default: object: 0, scene: 1)" in text
    assert "(default: object: 200, scene: 400)" in text  # steps


def test_options_can_be_made_for_any_config_and_unset_change_nothing() -> None:
    options = preset_options(NeuralSDFConfig, {"a": NeuralSDFConfig(), "b": NeuralSDFConfig(levels=2)})
    assert {f.name for f in dataclasses.fields(options)} == {f.name for f in dataclasses.fields(NeuralSDFConfig)}
    assert with_options(NeuralSDFConfig(levels=2), options()) == NeuralSDFConfig(levels=2)


def test_a_bad_nested_value_is_refused_by_its_own_config() -> None:
    options = tyro.cli(TRAINING_OPTIONS, args=["--architecture.encoding", "octree"])
    with pytest.raises(RegnfError, match="unknown encoding 'octree'"):
        with_options(SCENE_RGBD, options)
