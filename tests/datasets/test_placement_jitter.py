"""Placement jitter of generated variants, against independent truths.

The draws: rotations about the up axis and moves within the support plane checked with
scipy's rotations and plain vector algebra. The collision test: analytic boxes (a floor, a
wall, two boxes as instances), whose kept placements are checked with closed-form box
inclusion on points filling each box. The data set: a jittered run against an unjittered one
of the same seeds, its layers read back by USD and traced again, its BOP poses inverted by hand.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from regnf.compositor.cameras_io import OrbitConfig, field_bounds_metres
from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.render_folder import RenderConfig, render_views
from regnf.compositor.replace import pick_replacements
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.compositor.substitution import SubstitutedInstance, build_composite
from regnf.core.executors import ExecutorConfig
from regnf.core.image_io import read_instance_png
from regnf.datasets.generation import GenerateConfig, generate, variant_cameras
from regnf.datasets.manifest import load_rows
from regnf.datasets.placement_jitter import STREAM, candidates, collision_test, draw_placements
from regnf.datasets.variation import draw_appearance
from regnf.fields.analytic import Box, Union
from regnf.scene_graph import ProxyMesh, add_instance, read_stage
from tests.cli.cli_helpers import assert_fails
from tests.scene_graph.helpers import make_stage, similarity

ORBIT = OrbitConfig(n=3, width=24, height=18, radius=4.5)
"""Cameras well outside the tiny scene blob (as tests/datasets/test_generate.py has them)."""


# -- the draws ------------------------------------------------------------------------------

def test_the_same_seed_draws_the_same_placements_and_the_stream_is_the_jitter_s_own() -> None:
    poses = {"b": similarity(0.3, (1.0, 2.0, 0.0), 1.2), "a": similarity(-1.0, (-1.0, 0.5, 0.0), 0.8)}
    first = draw_placements(5, poses, 20.0, 0.1)
    again = draw_placements(5, poses, 20.0, 0.1)
    other = draw_placements(6, poses, 20.0, 0.1)
    assert list(first) == ["a", "b"]  # sorted ids
    for iid in poses:
        np.testing.assert_array_equal(first[iid].object_to_scene, again[iid].object_to_scene)
        assert first[iid].yaw_deg == again[iid].yaw_deg and first[iid].moved
        assert first[iid].yaw_deg != other[iid].yaw_deg
    # What "a" found free or not does not change what "b" draws: every instance draws all its
    # candidates up front, whatever is kept.
    blocked = draw_placements(5, poses, 20.0, 0.1, lambda iid, c, o: np.full(len(c), iid == "a"))
    assert not blocked["a"].moved and blocked["a"].yaw_deg == 0.0 and blocked["a"].shift_m == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(blocked["a"].object_to_scene, poses["a"])
    np.testing.assert_array_equal(blocked["b"].object_to_scene, first["b"].object_to_scene)
    # The first free candidate is kept: with the first 7 refused, the 8th of the same draws.
    calls = []

    def refuse_first_seven(iid: str, cand: np.ndarray, others: dict) -> np.ndarray:
        calls.append(len(cand))
        return np.arange(sum(calls) - len(cand), sum(calls)) < 7 if iid == "a" else np.zeros(len(cand), bool)

    late = draw_placements(5, poses, 20.0, 0.1, refuse_first_seven)
    rng = np.random.default_rng([5, STREAM])
    cand, yaw, _ = candidates(poses["a"], rng.random((20, 3)), 20.0, 0.1)
    np.testing.assert_allclose(late["a"].object_to_scene, cand[7])
    assert late["a"].yaw_deg == pytest.approx(yaw[7])
    # Off: nothing moves.
    off = draw_placements(5, poses, 0.0, 0.0)
    assert not any(p.moved for p in off.values())
    for bad in ((181.0, 0.0), (-1.0, 0.0), (0.0, 0.6), (0.0, float("nan"))):
        with pytest.raises(ValueError):
            draw_placements(0, poses, *bad)


def test_a_placement_turns_about_the_up_axis_and_moves_its_base_within_the_plane() -> None:
    # A tilted instance: its up axis is not the scene's +Z, and its scale is not 1.
    pose = similarity(0.7, (0.4, -1.2, 0.3), 1.3, tilt=0.35)
    up = pose[:3, 2] / np.linalg.norm(pose[:3, 2])
    u = np.random.default_rng(1).random((4000, 3))
    poses, yaw, shift = candidates(pose, u, 25.0, 0.08)
    assert (np.abs(yaw) <= 25.0).all() and yaw.min() < -24.0 and yaw.max() > 24.0
    r = np.linalg.norm(shift, axis=1)
    assert (r <= 0.08 + 1e-12).all() and r.max() > 0.079
    # Uniform over the disk: a quarter of the draws within half the radius.
    assert abs((r < 0.04).mean() - 0.25) < 0.03
    for k in range(0, 4000, 97):
        R = Rotation.from_rotvec(math.radians(yaw[k]) * up).as_matrix()
        np.testing.assert_allclose(poses[k][:3, :3], R @ pose[:3, :3], atol=1e-12)
        np.testing.assert_allclose(poses[k][:3, 3], pose[:3, 3] + shift[k], atol=1e-12)
        np.testing.assert_allclose(poses[k][3], [0, 0, 0, 1])
        assert abs(shift[k] @ up) < 1e-12  # within the support plane
        # Scale and the up axis kept.
        np.testing.assert_allclose(np.linalg.norm(poses[k][:3, :3], axis=0), 1.3, atol=1e-12)
        np.testing.assert_allclose(poses[k][:3, 2], pose[:3, 2], atol=1e-12)
    # Through draw_placements: what is recorded is what was applied.
    placed = draw_placements(3, {"i": pose}, 25.0, 0.08)["i"]
    np.testing.assert_allclose(placed.object_to_scene[:3, 3] - pose[:3, 3], placed.shift_m, atol=1e-12)
    R = Rotation.from_rotvec(math.radians(placed.yaw_deg) * up).as_matrix()
    np.testing.assert_allclose(placed.object_to_scene[:3, :3], R @ pose[:3, :3], atol=1e-12)


# -- the collision test ---------------------------------------------------------------------

HALF = np.array([0.25, 0.25, 0.4])
"""Half extents of the instances' boxes, metres (they stand on z = 0)."""
WALL_X = 0.95
"""The wall's face towards the instances: x = 0.95 (it is 0.1 m thick, 2 m high)."""


def box_proxy(half: np.ndarray) -> ProxyMesh:
    """A box mesh standing on z = 0 (8 vertices, 12 triangles, outward)."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (0, 2)], dtype=np.float64) * half
    faces = [[0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]]
    return ProxyMesh(corners.astype(np.float32), np.asarray(faces, dtype=np.int32))


def box_scene(poses: dict[str, np.ndarray]) -> tuple:
    """A composite of a floor and a wall with a box instance at each pose, and its collision test."""
    floor = Box((3.0, 3.0, 0.05), (0.0, 0.0, -0.05))
    wall = Box((0.05, 3.0, 1.0), (WALL_X + 0.05, 0.0, 1.0))
    room = Union(floor, wall)
    obj = Box(tuple(HALF), (0.0, 0.0, HALF[2]))  # field frame = canonical object metres
    specs = [SubstitutedInstance(k, obj, obj, pose, name=iid) for k, (iid, pose) in enumerate(poses.items(), 1)]
    comp = build_composite(room, specs, StageCompositeConfig())
    ids = {iid: k for k, iid in enumerate(poses, 1)}
    return collision_test(comp, {iid: box_proxy(HALF) for iid in poses}, ids)


def filling(pose: np.ndarray, n: int = 9) -> np.ndarray:
    """(n**3, 3) points filling the instance box at ``pose``, scene metres."""
    g = np.linspace(-1.0, 1.0, n)
    p = np.stack(np.meshgrid(g, g, (g + 1.0)), axis=-1).reshape(-1, 3) * HALF
    return p @ pose[:3, :3].T + pose[:3, 3]


def deepest(points: np.ndarray, pose: np.ndarray) -> float:
    """How deep (metres, 0 if not inside) the deepest of ``points`` lies in the box at ``pose``:
    the smallest distance to its faces of a point inside, in its own frame."""
    local = (points - pose[:3, 3]) @ pose[:3, :3]  # rotation only (scale 1)
    local[:, 2] -= HALF[2]
    depth = (HALF - np.abs(local)).min(axis=1)
    return float(max(depth.max(), 0.0))


def overlap(poses: dict[str, np.ndarray]) -> float:
    """Deepest penetration (metres) between the boxes, or of a box into the wall."""
    worst = 0.0
    for i, a in poses.items():
        pa = filling(a)
        worst = max(worst, float((pa[:, 0] - WALL_X).max()))
        for j, b in poses.items():
            if i != j:
                worst = max(worst, deepest(pa, b))
    return worst


def test_kept_placements_collide_with_nothing_and_a_boxed_in_instance_stays() -> None:
    # Box "a" 0.15 m from the wall and 0.15 m from box "b": moves of 0.3 m often collide.
    poses = {"a": similarity(0.0, (0.55, 0.0, 0.0), 1.0), "b": similarity(0.2, (-0.1, 0.05, 0.0), 1.0)}
    assert overlap(poses) <= 0.0
    test = box_scene(poses)
    moved, would_collide = 0, 0
    for seed in range(12):
        placed = draw_placements(seed, poses, 45.0, 0.3, test)
        final = {i: p.object_to_scene for i, p in placed.items()}
        # Within the test's tolerance (0.01 m) and the spacing of its points.
        assert overlap(final) < 0.02, (seed, {i: (p.yaw_deg, p.shift_m) for i, p in placed.items()})
        moved += sum(p.moved for p in placed.values())
        blind = draw_placements(seed, poses, 45.0, 0.3)  # the same draws, nothing refused
        would_collide += overlap({i: p.object_to_scene for i, p in blind.items()}) > 0.05
    assert moved >= 12, "almost nothing moved"
    assert would_collide >= 3, "the draws never collide: the test shows nothing"

    # Two boxes sunk 0.06 m into each other, moved at most 0.02 m: no free place, both stay.
    stuck = {"c": similarity(0.0, (-1.0, -1.5, 0.0), 1.0), "d": similarity(0.0, (-0.56, -1.5, 0.0), 1.0)}
    placed = draw_placements(0, stuck, 0.0, 0.02, box_scene(stuck))
    for iid, pose in stuck.items():
        assert not placed[iid].moved and placed[iid].shift_m == (0.0, 0.0, 0.0)
        np.testing.assert_array_equal(placed[iid].object_to_scene, pose)


# -- a data set -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """The stage of tests/datasets/test_generate.py, generated twice: plain and jittered (2 variants)."""
    tmp = tmp_path_factory.mktemp("jitter")
    stage = make_stage(tmp, names=("c", "dc", "fc", "fc-nop", "t"))
    add_instance(stage, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(stage, "dc", similarity(1.5, (-2.2, 0.4, 0.0), 1.0))
    add_instance(stage, "t", similarity(-0.3, (0.3, 2.3, 0.0), 1.0))
    for name, (yaw, shift) in {"plain": (0.0, 0.0), "jittered": (30.0, 0.2)}.items():
        cfg = jitter_config(yaw, shift)
        report = generate(stage, tmp / name, cfg, progress=False)
        assert report.made == [0, 1] and not report.failed
    return stage, tmp / "plain", tmp / "jittered"


def jitter_config(yaw: float, shift: float) -> GenerateConfig:
    return GenerateConfig(variants=2, cameras=ORBIT, format="nerfstudio,bop", jitter_yaw_deg=yaw,
                          jitter_shift=shift, exposure_stops=0.5,
                          executor=ExecutorConfig(kind="local", workers=2))


def test_a_jittered_data_set_records_shows_and_labels_the_moved_instances(runs: tuple[Path, Path, Path]) -> None:
    stage, plain, jittered = runs
    base = read_stage(stage)
    settings = [json.loads((d / "generation.json").read_text())["settings"] for d in (plain, jittered)]
    assert "placement" not in settings[0]
    assert settings[1]["placement"] == {"jitter_yaw_deg": 30.0, "jitter_shift": 0.2}
    rows = {name: load_rows(d) for name, d in (("plain", plain), ("jittered", jittered))}
    moved_any = 0
    for p_row, j_row in zip(rows["plain"], rows["jittered"], strict=True):
        seed = j_row["seed"]
        assert "placement" not in p_row
        # Selections and appearance are the seed's, jitter or not.
        assert j_row["selections"] == p_row["selections"] == pick_replacements(base, seed)
        assert j_row["appearance"]["exposure_stops"] == draw_appearance(seed, 0.5, 0.0).stops
        assert sorted(j_row["placement"]) == sorted(base.instances)
        layered = read_stage(jittered / j_row["layer"])
        folder = jittered / j_row["variant"]
        cams = json.loads((folder / "render.json").read_text())["cameras"]
        gts = json.loads((jittered / "bop" / "train" / f"{seed:06d}" / "scene_gt.json").read_text())
        for iid, entry in j_row["placement"].items():
            O0, O = base.instances[iid].object_to_scene, np.asarray(entry["object_to_scene"])
            assert abs(entry["yaw_deg"]) <= 30.0 and np.linalg.norm(entry["shift_m"]) <= 0.2 + 1e-12
            np.testing.assert_allclose(O[:3, 3] - O0[:3, 3], entry["shift_m"], atol=1e-12)
            R = Rotation.from_rotvec(math.radians(entry["yaw_deg"]) * np.array([0.0, 0.0, 1.0])).as_matrix()
            np.testing.assert_allclose(O[:3, :3], R @ O0[:3, :3], atol=1e-12)
            assert entry["moved"] or (entry["yaw_deg"] == 0.0 and np.array_equal(O, O0))
            moved_any += entry["moved"]
            # The layer, as USD reads it, holds the pose shown.
            np.testing.assert_allclose(layered.instances[iid].object_to_scene, O, atol=1e-9)
            # The 3D box: the proxy's extent placed by hand.
            lib = base.library[j_row["selections"][iid]]
            lo, hi = lib.proxy.extent.astype(np.float64)
            box = j_row["boxes"][iid]
            np.testing.assert_allclose(box["center"], O[:3, :3] @ ((lo + hi) / 2) + O[:3, 3], atol=1e-5)
            np.testing.assert_allclose(box["rotation"], O[:3, :3], atol=1e-6)  # scale 1
            np.testing.assert_allclose(box["half_extents"], (hi - lo) / 2, atol=1e-5)
            # BOP: every view's pose, taken back to the room by hand, is the pose shown.
            iid_n = j_row["instance_ids"][iid]
            g = sorted(j_row["instance_ids"].values()).index(iid_n)
            for k, cam in enumerate(cams):
                c2w = np.asarray(cam["camera_to_world"], dtype=np.float64)
                gt = gts[str(k)][g]
                Rm = c2w[:3, :3] @ np.asarray(gt["cam_R_m2c"]).reshape(3, 3)
                tm = c2w[:3, :3] @ (np.asarray(gt["cam_t_m2c"]) / 1000.0) + c2w[:3, 3]
                np.testing.assert_allclose(Rm, O[:3, :3], atol=1e-6)
                np.testing.assert_allclose(tm, O[:3, :3] @ ((lo + hi) / 2) + O[:3, 3], atol=1e-5)
            # The instance's pixels moved when it did.
            if entry["moved"]:
                ious = []
                for k in range(len(cams)):
                    a = read_instance_png(plain / p_row["variant"] / f"instance_{k:04d}.png") == iid_n
                    b = read_instance_png(folder / f"instance_{k:04d}.png") == iid_n
                    if (a | b).any():
                        ious.append((a & b).sum() / (a | b).sum())
                assert ious and min(ious) < 1.0, (seed, iid, ious)
    assert moved_any >= 2


def test_a_jittered_layer_composes_to_the_views_it_was_made_with(runs: tuple[Path, Path, Path]) -> None:
    stage, _, jittered = runs
    row = load_rows(jittered)[0]
    assert any(e["moved"] for e in row["placement"].values())
    layer = composite_from_stage(jittered / row["layer"])
    below = composite_from_stage(stage)
    # The originals are removed where they were captured, not where the objects now stand.
    assert len(layer.field.removals) == len(below.field.removals)
    x = torch.rand(4000, 3, dtype=torch.float32) * 2.0 - 1.0
    with torch.no_grad():
        np.testing.assert_array_equal(layer.field.scene_masked(x).sdf.numpy(), below.field.scene_masked(x).sdf.numpy())
    cfg = jitter_config(30.0, 0.2)
    bounds = field_bounds_metres(composite_from_stage(stage, StageCompositeConfig(mode="scene")).field.scene)
    cams = variant_cameras(bounds, cfg, row["seed"])
    out = jittered.parent / "traced_again"
    render_views(layer.field, cams, out, RenderConfig(progress=False, views_per_trace=16))
    for k in range(len(cams)):
        np.testing.assert_array_equal(read_instance_png(out / f"instance_{k:04d}.png"),
                                      read_instance_png(jittered / row["variant"] / f"instance_{k:04d}.png"))


def test_jitter_ranges_are_refused_before_any_work(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out = tmp_path / "never"
    assert_fails(capsys, ["generate", str(tmp_path / "no-stage.usda"), "--out", str(out), "--jitter-shift", "0.8"],
                 r"^regnf generate: jitter_shift must be between 0 and 0\.5 metres, got 0\.8$")
    assert_fails(capsys, ["generate", str(tmp_path / "no-stage.usda"), "--out", str(out), "--jitter-yaw-deg", "-5"],
                 r"^regnf generate: jitter_yaw_deg must be between 0 and 180 degrees, got -5\.0$")
    assert not out.exists()
