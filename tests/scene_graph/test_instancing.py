"""Instancing and replacement: 4 instances of 2 objects share 2 prototypes; a replacement layer
switches variant selections, which changes the referenced field and nothing else; a swapped
object stands on the floor with the same heading; cross-class swaps need force."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from regnf.scene_graph import (
    StageError,
    add_instance,
    make_replacement_layer,
    read_stage,
    set_instance,
)

from .helpers import OBJECTS, make_stage, similarity, snapshot

FLOOR_Z = 0.0
POSES = {
    "a": ("c", similarity(0.3, (1.0, 2.0, FLOOR_Z), 1.0)),
    "b": ("c", similarity(2.0, (-1.0, 1.5, FLOOR_Z), 1.0)),
    "c": ("dc", similarity(-1.0, (0.5, -1.0, FLOOR_Z), 1.02)),
    "d": ("dc", similarity(3.0, (2.0, -2.0, FLOOR_Z), 0.98)),
}


@pytest.fixture(scope="module")
def stage_path(tmp_path_factory):
    folder = tmp_path_factory.mktemp("inst")
    path = make_stage(folder, ("c", "dc", "fc-nop", "t"))
    for iid, (name, M) in POSES.items():
        add_instance(path, name, M, instance_id=iid)
    return path


def _composed(stage: Usd.Stage) -> dict[str, object]:
    """Every attribute value of every prim (instance proxies included), by path."""
    out = {}
    for prim in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        for attr in prim.GetAttributes():
            v = attr.Get()
            out[str(attr.GetPath())] = np.array(v).tolist() if hasattr(v, "__len__") and not isinstance(v, str) else v
        out[str(prim.GetPath())] = prim.GetTypeName()
    return out


def test_four_instances_two_prototypes(stage_path):
    stage = Usd.Stage.Open(str(stage_path))
    instances = stage.GetPrimAtPath("/World/Instances").GetChildren()
    assert len(instances) == 4 and all(p.IsInstance() for p in instances)
    assert len(stage.GetPrototypes()) == 2
    protos = {p.GetName(): p.GetPrototype().GetPath() for p in instances}
    assert protos["a"] == protos["b"] != protos["c"] == protos["d"]


def test_switching_a_variant_changes_the_field_only(stage_path):
    out = stage_path.parent / "swap.usda"
    make_replacement_layer(stage_path, {"b": "fc-nop"}, out)
    before = _composed(Usd.Stage.Open(str(stage_path)))
    after_stage = Usd.Stage.Open(str(out))
    after = _composed(after_stage)
    changed = {k for k in before.keys() | after.keys() if before.get(k) != after.get(k)}
    # Only the field of instance b (its field attributes, its name label and the proxy below it) changed.
    allowed = ("/World/Instances/b.regnf:field:", "/World/Instances/b/Proxy",
               "/World/Instances/b.semantics:labels:name", "/World/Instances/b.semantic:name:")
    assert changed and all(k.startswith(allowed) for k in changed), sorted(changed)[:10]
    b = after_stage.GetPrimAtPath("/World/Instances/b")
    assert b.GetAttribute("regnf:field:checkpoint").Get().path == "../fields/fc-nop.safetensors"
    assert b.GetAttribute("regnf:field:name").Get() == "fc-nop"
    # Still instanced: a, and the two dc now share with nobody new; b has its own prototype.
    assert len(after_stage.GetPrototypes()) == 3
    # The layer is small: only overs with variant selections.
    text = out.read_text()
    assert "fc-nop" in text and "xformOp" not in text and "points" not in text
    swapped = read_stage(out)
    assert swapped.instances["b"].library_name == "fc-nop"
    assert {k: v.library_name for k, v in swapped.instances.items() if k != "b"} == {"a": "c", "c": "dc", "d": "dc"}
    np.testing.assert_array_equal(swapped.instances["b"].object_to_scene, POSES["b"][1])


def test_swapped_object_stands_on_the_floor_with_the_same_heading(stage_path):
    out = stage_path.parent / "swap_c.usda"
    make_replacement_layer(stage_path, {"c": "fc-nop"}, out)
    for path, name in ((stage_path, "dc"), (out, "fc-nop")):
        stage = Usd.Stage.Open(str(path))
        prim = stage.GetPrimAtPath("/World/Instances/c")
        cache = UsdGeom.XformCache()
        mesh = prim.GetChild("Proxy")
        world = np.array(cache.GetLocalToWorldTransform(mesh)).T
        pts = np.array(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), dtype=np.float64)
        pts_w = pts @ world[:3, :3].T + world[:3, 3]
        assert abs(pts_w[:, 2].min() - FLOOR_Z) < 1e-6, name  # base on the floor
        heading = world[:3, 0] / np.linalg.norm(world[:3, 0])
        np.testing.assert_allclose(heading, np.array([np.cos(-1.0), np.sin(-1.0), 0.0]), atol=1e-9)
        size = pts_w.max(0) - pts_w.min(0)
        assert abs(size[2] - OBJECTS[name][2][2] * 1.02) < 1e-5  # each object keeps its own size


def test_cross_class_swap_refused_unless_forced(stage_path):
    out = stage_path.parent / "to_table.usda"
    before = snapshot(stage_path.parent)
    with pytest.raises(StageError) as err:
        make_replacement_layer(stage_path, {"a": "t"}, out)
    msg = str(err.value)
    assert "/World/Instances/a" in msg and str(stage_path) in msg and "chair" in msg and "table" in msg
    assert snapshot(stage_path.parent) == before and not out.exists()
    make_replacement_layer(stage_path, {"a": "t"}, out, force=True)
    forced = read_stage(out)
    assert forced.instances["a"].library_name == "t"
    stage = Usd.Stage.Open(str(out))
    assert stage.GetPrimAtPath("/World/Instances/a").GetAttribute("regnf:slot:class").Get() == "table"


def test_replacement_errors_name_prim_and_file(stage_path, tmp_path):
    with pytest.raises(StageError, match="/World/Instances/zz"):
        make_replacement_layer(stage_path, {"zz": "c"}, stage_path.parent / "x.usda")
    with pytest.raises(StageError, match="'nope' is not in the stage's library"):
        make_replacement_layer(stage_path, {"a": "nope"}, stage_path.parent / "x.usda")
    with pytest.raises(StageError, match="escape"):
        make_replacement_layer(stage_path, {"a": "dc"}, tmp_path / "elsewhere.usda")
    assert not (stage_path.parent / "x.usda").exists() and not (tmp_path / "elsewhere.usda").exists()


def test_set_instance_moves_one_instance_and_keeps_the_rest(tmp_path):
    path = make_stage(tmp_path, ("c", "dc"))
    add_instance(path, "c", similarity(0.3, (1.0, 2.0, FLOOR_Z), 1.0), instance_id="a")
    add_instance(path, "dc", similarity(-1.0, (0.5, -1.0, FLOOR_Z), 1.02), instance_id="b")
    before = read_stage(path)
    moved = similarity(1.2, (0.7, 0.1, FLOOR_Z), 0.97)
    set_instance(path, "a", moved)
    after = read_stage(path)
    np.testing.assert_allclose(after.instances["a"].object_to_scene, moved, atol=1e-12)
    assert after.instances["a"].library_name == "c" and after.instances["a"].registration is None
    np.testing.assert_array_equal(after.instances["b"].object_to_scene, before.instances["b"].object_to_scene)
    assert list(after.instances) == ["a", "b"] and sorted(after.library) == sorted(before.library)
    files = snapshot(path.parent)
    with pytest.raises(StageError, match="no such instance"):
        set_instance(path, "zz", moved)
    with pytest.raises(StageError):
        set_instance(path, "a", np.diag([1.0, 2.0, 1.0, 1.0]))  # not a similarity
    assert snapshot(path.parent) == files  # a refused edit leaves every file as it was
