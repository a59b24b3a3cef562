"""The ``regnf`` command line: help, the cache (nothing made twice), train / distill / mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from regnf.cli.app import main
from regnf.io.checkpoint import load_field
from regnf.meshes.source_mesh import read_source_mesh, source_mesh_file
from tests.cli.cli_helpers import assert_fails
from tests.observations.capture_helpers import write_analytic_capture


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for cmd in ("synth", "train", "distill", "mesh", "register", "render", "replace", "bench fields",
                "bench registration"):
        assert cmd in out


def test_unknown_command_is_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["no-such-command"]) == 2
    assert "unknown command" in capsys.readouterr().err


def test_version_is_the_installed_packages(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"regnf {version('regnf')}"


@pytest.mark.parametrize("group", ["stage", "bench"])
def test_a_group_lists_its_subcommands(capsys: pytest.CaptureFixture[str], group: str) -> None:
    assert main([group, "--help"]) == 0
    listed = [line.split()[1] for line in capsys.readouterr().out.splitlines() if line.startswith(f"  {group} ")]
    expected = {"stage": ["new", "add-instance", "show", "export"]}.get(group)
    assert listed == expected if expected else len(listed) >= 5
    assert main([group]) == 2  # a group alone names no command
    assert f"{group} " in capsys.readouterr().err


def test_without_the_benchmarks_bench_says_where_they_are(monkeypatch: pytest.MonkeyPatch,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    # An install from the wheel has no regnf.benchmarks: every other command still works.
    import sys

    for name in ("regnf.benchmarks", "regnf.benchmarks.cli"):
        monkeypatch.setitem(sys.modules, name, None)  # importing it now fails
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "  train " in out and "bench" not in out
    for args in (["bench", "fields"], ["bench", "--help"], ["bench"]):
        assert main(args) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "source checkout" in err and "pip install -e ." in err


def test_a_value_error_from_a_dependency_is_an_internal_error(monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    # Only regnf's own errors (RegnfError) are the user's bad input; a ValueError raised inside a
    # dependency is a bug in how regnf called it.
    from regnf.cli import commands_capture
    from regnf.core.errors import RegnfError

    def fails(error: Exception):
        def run(self: object) -> None:
            raise error
        return run

    for error, status in ((ValueError("operands could not be broadcast"), 70), (RegnfError("x.json: bad"), 1)):
        monkeypatch.setattr(commands_capture.InspectCapture, "run", fails(error))
        assert main(["inspect-capture", "somewhere"]) == status
        err = capsys.readouterr().err.strip()
        if status == 70:
            assert "internal error" in err and "--debug" in err
        else:
            assert err == "regnf inspect-capture: x.json: bad"


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="this machine has CUDA")
def test_a_cuda_device_without_cuda_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Refused before the (missing) stage is even read.
    assert main(["render", str(tmp_path / "none.usda"), "--device", "cuda", "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("regnf render: --device cuda: CUDA is not available")
    assert not (tmp_path / "o").exists()


def test_command_help_explains_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--cache-dir" in out and "Cache directory" in out


def checkpoints(cache: Path) -> list[Path]:
    """The cache's field checkpoints (not the source meshes kept beside them)."""
    return sorted(p for p in (cache / "fields").glob("*.safetensors") if not p.name.endswith(".source-mesh.safetensors"))


def test_distill_uses_the_cache_and_meshes(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    box.apply_translation((0.0, 0.0, 0.1))
    mesh_path = tmp_path / "box.ply"
    box.export(mesh_path)
    cache = tmp_path / "cache"
    args = ["distill", "--mesh", str(mesh_path), "--distillation.steps", "5", "--label", "box", "--cache-dir", str(cache)]
    assert main([*args, "--out", str(tmp_path / "a.safetensors")]) == 0
    made = checkpoints(cache)
    assert len(made) == 1
    # The mesh comes along for other tools, in the cache and beside --out.
    kept = source_mesh_file(made[0])
    assert source_mesh_file(tmp_path / "a.safetensors").read_bytes() == kept.read_bytes()
    np.testing.assert_allclose(read_source_mesh(made[0]).points, box.vertices, atol=1e-6)
    stamp = made[0].stat().st_mtime_ns
    # Same mesh, same settings: reused, not distilled again.
    assert main([*args, "--out", str(tmp_path / "b.safetensors")]) == 0
    assert checkpoints(cache) == made
    assert made[0].stat().st_mtime_ns == stamp
    assert (tmp_path / "a.safetensors").read_bytes() == made[0].read_bytes() == (tmp_path / "b.safetensors").read_bytes()
    assert load_field(tmp_path / "a.safetensors").label == "box"
    # A different setting is a different field.
    assert main([*args[:-2], "--distillation.steps", "6", "--cache-dir", str(cache)]) == 0
    assert len(checkpoints(cache)) == 2
    assert main(["mesh", "--field", str(made[0]), "--out", str(tmp_path / "m.ply"), "--resolution", "32"]) == 0
    assert len(trimesh.load(tmp_path / "m.ply").faces) > 0


def test_distill_rejects_a_missing_mesh(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert_fails(capsys, ["distill", "--mesh", str(tmp_path / "nope.ply"), "--cache-dir", str(tmp_path)], "no such mesh file")


def test_train_from_a_capture_folder(tmp_path: Path) -> None:
    capture = write_analytic_capture(tmp_path / "cap")
    root = capture.root
    cache = tmp_path / "cache"
    args = ["train", "--capture", str(root), "--training.steps", "3", "--cache-dir", str(cache)]
    assert main([*args, "--out", str(tmp_path / "f.safetensors")]) == 0
    field = load_field(tmp_path / "f.safetensors")
    assert field.info.provenance["trained_from"] == "rgbd"
    assert main(args) == 0  # reused
    assert len(list((cache / "fields").glob("*.safetensors"))) == 1
    # The edge loss is a training setting: another field, with the weight in its provenance.
    assert main([*args, "--training.w-edge", "1", "--out", str(tmp_path / "e.safetensors")]) == 0
    assert len(checkpoints(cache)) == 2
    assert load_field(tmp_path / "e.safetensors").info.provenance["train_config"]["w_edge"] == 1.0
    assert main([*args, "--training.w-outline", "1", "--out", str(tmp_path / "o.safetensors")]) == 0
    assert len(list((cache / "fields").glob("*.safetensors"))) == 3
    assert load_field(tmp_path / "o.safetensors").info.provenance["train_config"]["w_outline"] == 1.0
    assert main([*args, "--training.carve-every", "1", "--out", str(tmp_path / "p.safetensors")]) == 0
    assert len(list((cache / "fields").glob("*.safetensors"))) == 4
    assert load_field(tmp_path / "p.safetensors").info.provenance["train_config"]["carve_every"] == 1


def test_train_rejects_a_negative_carve_interval(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = write_analytic_capture(tmp_path / "cap")
    assert_fails(capsys, ["train", "--capture", str(capture.root), "--training.carve-every", "-1",
                          "--cache-dir", str(tmp_path / "cache")], "RGBDTrainConfig.carve_every must be")


@pytest.mark.parametrize("option", ["w-edge", "w-outline"])
@pytest.mark.parametrize("weight", ["-1", "nan", "inf"])
def test_train_rejects_a_bad_loss_weight(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
                                         weight: str) -> None:
    capture = write_analytic_capture(tmp_path / "cap")
    assert_fails(capsys, ["train", "--capture", str(capture.root), f"--training.{option}", weight,
                          "--cache-dir", str(tmp_path / "cache")], f"RGBDTrainConfig.{option.replace('-', '_')} must be")


def test_cache_keys_ignore_new_options_left_at_their_default() -> None:
    import dataclasses

    from regnf.synthetic.cache import config_key
    from regnf.training.presets import object_rgbd_preset
    from regnf.training.training import RGBDTrainConfig

    cfg = object_rgbd_preset()
    assert config_key(cfg) == config_key(dataclasses.replace(cfg))
    assert config_key(cfg) != config_key(dataclasses.replace(cfg, steps=cfg.steps + 1))
    assert config_key(cfg) != config_key(dataclasses.replace(cfg, w_volume_color=0.5))
    # An option at its default contributes nothing to the key.
    assert config_key(RGBDTrainConfig()) == config_key(RGBDTrainConfig(w_volume_color=0.0))


def test_help_into_a_reader_that_stops_early_is_no_error() -> None:
    import subprocess
    import sys

    run = subprocess.Popen([sys.executable, "-m", "regnf", "discover", "--help-all"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE)
    assert run.stdout.readline().startswith(b"usage: regnf discover")  # help longer than a pipe holds
    run.stdout.close()  # as `| head -1` does
    _, err = run.communicate(timeout=120)
    assert run.returncode == 0 and b"Traceback" not in err, err.decode()[-2000:]


@pytest.mark.parametrize("args", [["--help"], ["stage", "--help"], ["bench", "--help"], ["train", "--help"]])
def test_output_into_a_closed_pipe_is_no_error(args: list[str]) -> None:
    import subprocess
    import sys

    run = subprocess.Popen([sys.executable, "-m", "regnf", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    run.stdout.close()  # closed before the command writes anything: its first write fails
    _, err = run.communicate(timeout=120)
    assert run.returncode == 0 and err == b"", err.decode()[-2000:]


def test_a_commands_output_into_a_closed_pipe_is_no_error(tmp_path: Path) -> None:
    import subprocess
    import sys

    from tests.scene_graph.helpers import make_stage

    stage = make_stage(tmp_path / "s", ("c", "t"))
    run = subprocess.Popen([sys.executable, "-m", "regnf", "stage", "show", str(stage)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE)
    run.stdout.close()  # `regnf stage show` prints its summary to stdout: the write fails
    _, err = run.communicate(timeout=120)
    assert run.returncode == 0 and err == b"", err.decode()[-2000:]


def test_no_sphinx_markup_in_any_help(capsys: pytest.CaptureFixture[str]) -> None:
    import re

    from regnf.cli.app import _commands

    for name in _commands():  # a loop over the commands
        assert main([*name.split(), "--help"]) == 0
        with pytest.raises(SystemExit):
            main([*name.split(), "--help-all"])
        for out in capsys.readouterr().out.split("usage: ")[1:]:  # the short help, then the full one
            assert out.startswith(f"regnf {name}"), name
            found = re.findall(r":(?:func|data|attr|mod|class|meth|obj|exc):`[^`]*", out)
            assert not found, (name, found[:3])


@pytest.mark.parametrize("command", ["generate", "replace"])
def test_commands_that_always_substitute_have_no_mode_option(tmp_path: Path, command: str) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([command, str(tmp_path / "s.usda"), "--out", str(tmp_path / "o"), "--composite.mode", "scene"])
    assert exit_info.value.code == 2 and not (tmp_path / "o").exists()


@pytest.mark.parametrize(("command", "config", "group"), [
    ("register", "regnf.registration.pipeline:RegistrationConfig", "registration"),
    ("discover", "regnf.registration.discovery:DiscoveryConfig", "discovery"),
])
def test_help_shows_the_commands_own_options_and_sums_up_each_group(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, command: str, config: str,
        group: str) -> None:
    import dataclasses
    import importlib
    import re

    from regnf.cli.app import _commands
    from tests.cli.cli_help import leaf_settings

    monkeypatch.setenv("COLUMNS", "100")
    assert main([command, "--help"]) == 0
    out = capsys.readouterr().out
    assert len(out.splitlines()) <= 60, len(out.splitlines())
    for f in dataclasses.fields(_commands()[command]):  # every option of the command's own level
        if f.name != group:
            assert re.search(rf"^│ --{f.name.replace('_', '-')}\b", out, re.MULTILINE), f.name
    assert not re.search(rf"^│ --{group}\.", out, re.MULTILINE)  # no option of the group is listed...
    module, name = config.split(":")
    settings = leaf_settings(getattr(importlib.import_module(module), name), f"--{group}.")
    # ... but the group is there, with the number of its settings, each in the full help.
    assert re.search(rf"{group} options \({len(settings)}, listed by --help-all\)", out), out[-600:]
    assert f"regnf {command} --help-all" in out
