"""Bad input: a clear StageError naming the prim and the file, and the stage on disk untouched
(missing or corrupted checkpoints, non-similarities, foreign stages, escaping paths, refused
registrations, a failure half way through a write)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

from regnf.scene_graph import (
    StageError,
    add_instance,
    add_instance_from_registration,
    new_stage,
    read_stage,
    transaction,
)
from regnf.scene_graph import usd_write as usd_write_module

from .helpers import checkpoint, make_library, make_stage, registration_json, similarity, snapshot


@pytest.fixture
def stage_path(tmp_path):
    path = make_stage(tmp_path)
    add_instance(path, "c", similarity(0.5, (1, 1, 0), 1.0), instance_id="a")
    return path


def test_missing_checkpoint(tmp_path):
    scene, _libs, proxies = make_library(tmp_path, ("c",))
    out = tmp_path / "stage" / "s.usda"
    with pytest.raises(StageError) as err:
        new_stage(out, scene, [tmp_path / "src" / "nothere.safetensors"], proxies=proxies)
    assert "nothere.safetensors" in str(err.value) and "does not exist" in str(err.value)
    assert "prim" in str(err.value)
    assert not (tmp_path / "stage").exists()


def test_corrupted_checkpoint_leaves_stage_alone(stage_path, tmp_path):
    bad = checkpoint(tmp_path, "dc", "chair")
    bad.write_bytes(bad.read_bytes()[:200])  # truncated
    before = snapshot(stage_path.parent)
    result = registration_json("dc", bad, similarity(0.0, (0, 0, 0), 1.0))
    result["library_name"] = "dc2"  # not in the library: it must be read from the checkpoint
    with pytest.raises(StageError) as err:
        add_instance_from_registration(stage_path, result)
    assert str(bad) in str(err.value) and "dc2" in str(err.value)
    assert snapshot(stage_path.parent) == before
    # A checkpoint of the stage itself corrupted after writing: reading names prim and file.
    ck = stage_path.parent / "fields" / "c.safetensors"
    ck.write_bytes(b"garbage" * 10)
    with pytest.raises(StageError) as err:
        read_stage(stage_path)
    assert str(ck) in str(err.value) and "prim /c" in str(err.value)


@pytest.mark.parametrize("bad", ["non-uniform", "negative", "shear"])
def test_non_similarity_refused(stage_path, bad):
    M = similarity(0.3, (1, 2, 0), 1.0)
    if bad == "non-uniform":
        M[:3, :3] = M[:3, :3] @ np.diag([1.0, 1.0, 2.0])
    elif bad == "negative":
        M[:3, :3] *= -1.0
    else:
        M[0, 1] += 0.3
    before = snapshot(stage_path.parent)
    with pytest.raises(StageError) as err:
        add_instance(stage_path, "c", M, instance_id="bad")
    assert "/World/Instances/bad" in str(err.value) and str(stage_path) in str(err.value)
    assert "not a similarity" in str(err.value)
    assert snapshot(stage_path.parent) == before


def test_refused_registration_and_forced(stage_path):
    lib = stage_path.parent / "fields" / "dc.safetensors"
    result = registration_json("dc", lib, similarity(1.0, (0, 1, 0), 1.0), accepted=False, confidence=0.21)
    before = snapshot(stage_path.parent)
    with pytest.raises(StageError) as err:
        add_instance_from_registration(stage_path, result)
    assert "not accepted" in str(err.value) and "0.210" in str(err.value) and str(stage_path) in str(err.value)
    assert snapshot(stage_path.parent) == before
    iid = add_instance_from_registration(stage_path, result, force=True)
    reg = read_stage(stage_path).instances[iid].registration
    assert reg.forced and not reg.accepted and reg.confidence == 0.21


def test_foreign_stage(tmp_path):
    path = tmp_path / "other.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Xform.Define(stage, "/World")
    UsdGeom.Cube.Define(stage, "/World/Cube")
    stage.GetRootLayer().Save()
    before = path.read_bytes()
    with pytest.raises(StageError, match="not a regnf stage"):
        read_stage(path)
    with pytest.raises(StageError, match=str(path)):
        add_instance(path, "c", np.eye(4))
    assert path.read_bytes() == before


def test_instance_without_our_attributes(stage_path):
    layer = Sdf.Layer.FindOrOpen(str(stage_path))
    layer.GetPrimAtPath("/World/Instances/a").RemoveProperty(
        layer.GetAttributeAtPath("/World/Instances/a.regnf:objectToScene"))
    layer.Save()
    with pytest.raises(StageError) as err:
        read_stage(stage_path)
    assert "/World/Instances/a" in str(err.value) and "regnf:objectToScene" in str(err.value)
    assert str(stage_path) in str(err.value)


def test_edited_ops_disagree(stage_path):
    layer = Sdf.Layer.FindOrOpen(str(stage_path))
    layer.GetAttributeAtPath("/World/Instances/a.xformOp:translate").default = (9.0, 9.0, 9.0)
    layer.Save()
    with pytest.raises(StageError, match="disagree"):
        read_stage(stage_path)


def test_escaping_paths(stage_path, tmp_path):
    outside = tmp_path / "outside.safetensors"
    outside.write_bytes((stage_path.parent / "fields" / "c.safetensors").read_bytes())
    lib = stage_path.parent / "library" / "c.usda"
    layer = Sdf.Layer.FindOrOpen(str(lib))
    rel = os.path.relpath(outside, lib.parent)
    assert rel.startswith("..")
    layer.GetAttributeAtPath("/c.regnf:field:checkpoint").default = Sdf.AssetPath(rel)
    layer.Save()
    with pytest.raises(StageError) as err:
        read_stage(stage_path)
    assert "escapes the stage's folder" in str(err.value) and str(lib) in str(err.value)
    assert "prim /c" in str(err.value)
    # The library table itself pointing outside.
    layer.GetAttributeAtPath("/c.regnf:field:checkpoint").default = Sdf.AssetPath("../fields/c.safetensors")
    layer.Save()
    root = Sdf.Layer.FindOrOpen(str(stage_path))
    data = dict(root.customLayerData)
    data["regnf"]["library"]["c"] = "../elsewhere/c.usda"
    root.customLayerData = data
    root.Save()
    with pytest.raises(StageError, match="escapes"):
        read_stage(stage_path)


def test_failure_during_commit_restores_everything(stage_path, tmp_path, monkeypatch):
    # A new library object: its checkpoint, asset layer, slot and the root layer all change.
    result = registration_json("fc-nop", checkpoint(tmp_path, "fc-nop", "chair"), similarity(0.1, (0, 0, 0), 1.0))
    before = snapshot(stage_path.parent)
    real_replace = os.replace
    calls = {"n": 0}

    def flaky(src, dst):
        calls["n"] += 1
        if calls["n"] == 2:  # after the first file has been replaced
            raise OSError("disk full (simulated)")
        return real_replace(src, dst)

    monkeypatch.setattr(transaction.os, "replace", flaky)
    with pytest.raises(OSError, match="simulated"):
        add_instance_from_registration(stage_path, result, instance_id="x")
    monkeypatch.undo()
    assert calls["n"] >= 2
    assert snapshot(stage_path.parent) == before


def test_failure_while_staging_leaves_no_trace(stage_path, monkeypatch):
    before = snapshot(stage_path.parent)

    def boom(*args, **kwargs):
        raise RuntimeError("exporter crashed (simulated)")

    monkeypatch.setattr(usd_write_module, "stage_layer", boom)
    with pytest.raises(RuntimeError, match="simulated"):
        add_instance(stage_path, "dc", similarity(0.1, (0, 0, 0), 1.0), instance_id="x")
    assert snapshot(stage_path.parent) == before


def test_discovery_record_round_trips_and_bad_ones_are_refused(stage_path):
    lib = stage_path.parent / "fields" / "dc.safetensors"
    record = {"found_by": "discovery", "candidate": 2, "chosen": "dc",
              "tried": [{"library": "dc", "screened": 0.61, "confidence": 0.83, "accepted": True},
                        {"library": "fc-nop", "screened": 0.2, "confidence": None, "accepted": None}]}
    result = {**registration_json("dc", lib, similarity(1.0, (0, 1, 0), 1.0)), "discovery": record}
    iid = add_instance_from_registration(stage_path, result)
    assert read_stage(stage_path).instances[iid].registration.discovery == record
    before = snapshot(stage_path.parent)
    for bad, words in (("a string", "'discovery' must be null or an object"),
                       ({"tried": [{"confidence": float("nan")}]}, r"confidence is nan \(not JSON\)"),
                       ({"what": object()}, "not JSON data")):
        with pytest.raises(StageError, match=words):
            add_instance_from_registration(stage_path, {**result, "discovery": bad})
    assert snapshot(stage_path.parent) == before
    # Edited by hand into something that is not JSON: reading names the prim and the file.
    text = stage_path.read_text()
    stage_path.write_text(text.replace('"found_by"', 'found_by', 1))
    with pytest.raises(StageError, match="regnf:registration:discovery' is not JSON") as err:
        read_stage(stage_path)
    assert str(stage_path) in str(err.value)
