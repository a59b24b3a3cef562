"""A library in millimetres against registration, the stage, ``replace`` and ``generate``.

Registration is scale-free: a chair modelled in millimetres is registered at scale 0.001 and
accepted. That scale is reported as a warning (console, JSON, the instance's provenance on
the stage); a swap that would put an object of another unit in its place (a thousand times
too large or too small) is refused before anything is rendered or written, unless asked for.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import regnf.cli.commands_registration as register_command
from regnf.cli.app import main
from regnf.compositor.size_change import SIZE_CHANGE_LIMIT
from regnf.fields.analytic import Transformed
from regnf.fields.similarity import similarity_matrix
from regnf.registration.scale_warnings import PLAUSIBLE_SCALE, scale_warnings
from regnf.scene_graph import (
    StageError,
    add_instance,
    add_instance_from_registration,
    new_stage,
    read_stage,
)
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails, run_cli
from tests.registration.fixtures import OBJECT_HI, OBJECT_LO, make_object, make_scene, placement
from tests.scene_graph.helpers import (
    OBJECTS,
    box_proxy,
    checkpoint,
    make_library,
    make_stage,
    registration_json,
    similarity,
)

MM = 1000.0
"""A library modelled in millimetres: its objects are 1000 of its units (metres, to the field) across."""
QUICK = ["--registration.no-upright", "--registration.init.ransac-runs", "1"]
"""A shorter initialisation: the exact analytic chair is registered all the same."""
VIEWS = ["--orbit", "1", "--orbit-radius", "4.5", "--width", "16", "--height", "12"]


def test_a_scale_far_from_one_is_a_warning_that_names_the_likely_unit() -> None:
    def warned(s: float) -> list[str]:
        return scale_warnings(similarity(0.4, (1.0, -2.0, 0.0), s))

    assert warned(1 / MM) == [("scale 0.0010: the library object is ~1000x its size in the scene; "
                               "is one of them in millimetres?")]
    assert warned(100.0) == [("scale 100: the library object is ~1/100 of its size in the scene; "
                              "is one of them in centimetres?")]
    assert warned(0.0254) == [("scale 0.0254: the library object is ~39x its size in the scene; "
                               "is one of them in inches?")]
    assert warned(0.2) == [("scale 0.2000: the library object is ~5.0x its size in the scene; "
                            "are they in different units?")]
    lo, hi = PLAUSIBLE_SCALE
    for s in (lo, 0.5, 1.0, 1.9, hi):  # copies of one object differ in size, not in units
        assert warned(s) == [], s


def test_register_warns_of_a_library_in_millimetres_and_the_stage_keeps_the_warning(tmp_path, capsys,
                                                                                     monkeypatch) -> None:
    stage = make_stage(tmp_path / "stage", ("c",))
    to_scene = placement([0, 0, 1], 0.7, [1.0, -0.5, 0.0], 1.0)
    chair_mm = Transformed(make_object(), np.asarray(similarity_matrix(np.eye(3), np.zeros(3), MM)),
                           name="cmm", label="chair")
    mm_path = checkpoint(tmp_path, "cmm", "chair", seed=5)  # what the stage reads of the object
    fields = {str(tmp_path / "room.safetensors"): make_scene(to_scene), str(mm_path): chair_mm}
    monkeypatch.setattr(register_command, "load_field", lambda path, device="cpu": fields[str(path)])
    corners = [(to_scene @ np.array([x, y, z, 1.0]))[:3].tolist()
               for x in (OBJECT_LO[0] - 0.05, OBJECT_HI[0] + 0.05) for y in (OBJECT_LO[1] - 0.05, OBJECT_HI[1] + 0.05)
               for z in (0.0, OBJECT_HI[2] + 0.05)]
    (tmp_path / "box.json").write_text(json.dumps({"corners": corners}))
    out = tmp_path / "registration.json"
    status, err = run_cli(capsys, ["register", "--scene", str(tmp_path / "room.safetensors"), "--library",
                                   str(mm_path), "--box", str(tmp_path / "box.json"), "--out", str(out),
                                   "--stage", str(stage), *QUICK])
    text = " ".join(err.split())
    assert status == 0, err
    expected = "scale 0.0010: the library object is ~1000x its size in the scene; is one of them in millimetres?"
    assert f"cmm_1: {expected}" in text
    saved = json.loads(out.read_text())
    assert saved["accepted"] is True and saved["warnings"] == [expected]
    assert read_stage(stage).instances["cmm_1"].registration.warnings == [expected]
    assert main(["stage", "show", str(stage)]) == 0
    assert f"warning: {expected}" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("warnings", ["scale 0.0010: one string, not a list", ["two\nlines"], [3]])
def test_a_registration_with_malformed_warnings_is_refused(tmp_path, warnings) -> None:
    stage = make_stage(tmp_path / "stage", ("c",))
    payload = {**registration_json("c", tmp_path / "stage" / "src" / "c.safetensors", similarity(0.0, (1, 0, 0), 1.0)),
               "warnings": warnings}
    before = snapshot(tmp_path)
    with pytest.raises(StageError, match="'warnings' must be a list of one-line strings"):
        add_instance_from_registration(stage, payload)
    assert not changes(before, snapshot(tmp_path))


@pytest.fixture(scope="module")
def mixed_stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A stage whose library holds the chair ``c`` in metres and ``cmm``, a chair in millimetres,
    with one instance of ``c``: any swap of that instance puts ``cmm`` in its place."""
    folder = tmp_path_factory.mktemp("mixed_units")
    scene, libs, proxies = make_library(folder, ("c",))
    libs.append(checkpoint(folder / "src", "cmm", "chair", seed=9))
    proxies["cmm"] = box_proxy(tuple(MM * v for v in OBJECTS["c"][2]))
    path = folder / "stage" / "scene.usda"
    new_stage(path, scene, libs, proxies=proxies)
    add_instance(path, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    return path


def _refusal(stage: Path) -> str:
    c = float(np.linalg.norm(OBJECTS["c"][2]))
    return (rf"{stage}: instance c_1: cmm would be {MM * c:.4g} m across where c is {c:.4g} m \(bounding-box "
            rf"diagonals at the instance's scale, 1\): 1000x, more than the {SIZE_CHANGE_LIMIT:g}x a swap may change; "
            r"is one library in other units\? \(swap anyway: allow_size_change, on the command line "
            r"--allow-size-change\)$")


def test_replace_refuses_to_swap_in_an_object_of_another_unit(mixed_stage, tmp_path, capsys) -> None:
    before = snapshot(mixed_stage.parent.parent), snapshot(tmp_path)
    line = assert_fails(capsys, ["replace", str(mixed_stage), "--out", str(tmp_path / "out"), *VIEWS],
                        _refusal(mixed_stage))
    assert line.startswith("regnf replace: ")
    assert not changes(before[0], snapshot(mixed_stage.parent.parent))
    assert not changes(before[1], snapshot(tmp_path))


def test_replace_swaps_it_when_told_to(mixed_stage, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    status, err = run_cli(capsys, ["replace", str(mixed_stage), "--out", str(out), "--allow-size-change", *VIEWS])
    assert status == 0, err
    assert read_stage(out / "replacement.usda").instances["c_1"].library_name == "cmm"


def test_generate_refuses_a_data_set_that_would_swap_in_an_object_of_another_unit(mixed_stage, tmp_path,
                                                                                  capsys) -> None:
    before = snapshot(mixed_stage.parent.parent), snapshot(tmp_path)
    line = assert_fails(capsys, ["generate", str(mixed_stage), "--out", str(tmp_path / "data"), "--variants", "1"],
                        _refusal(mixed_stage))
    assert line.startswith("regnf generate: ")
    assert not changes(before[0], snapshot(mixed_stage.parent.parent))
    assert not changes(before[1], snapshot(tmp_path))


def test_discover_warns_of_a_library_in_millimetres(tmp_path, capsys, monkeypatch) -> None:
    import regnf.cli.commands_discover as discover_command
    from tests.adversarial.test_discover import FAST

    src = tmp_path / "src"
    src.mkdir()
    room_path, mm_path = checkpoint(src, "room", "scene", scale=3.0), checkpoint(src, "cmm", "chair", seed=5)
    to_scene = placement([0, 0, 1], 0.7, [1.0, -0.5, 0.0], 1.0)
    chair_mm = Transformed(make_object(), np.asarray(similarity_matrix(np.eye(3), np.zeros(3), MM)),
                           name="cmm", label="chair")
    fields = {str(room_path): make_scene(to_scene), str(mm_path): chair_mm}
    monkeypatch.setattr(discover_command, "load_field", lambda path, device="cpu": fields[str(path)])
    out = tmp_path / "out"
    status, err = run_cli(capsys, ["discover", "--scene", str(room_path), "--library", str(mm_path),
                                   "--out", str(out), *FAST])
    assert status == 0, err
    expected = "scale 0.0010: the library object is ~1000x its size in the scene; is one of them in millimetres?"
    saved = json.loads((out / "discovery.json").read_text())
    found, = [c for c in saved["candidates"] if c["chosen"] is not None]
    assert found["chosen"] == "cmm" and found["warnings"] == [expected]
    assert saved["warnings"] == [f"candidate {found['candidate']} (cmm): {expected}"]
    assert f"candidate {found['candidate']} (cmm): {expected}" in " ".join(err.split())
    registered = json.loads((out / "registration" / f"candidate_{found['candidate']}.json").read_text())
    assert registered["warnings"] == [expected]
