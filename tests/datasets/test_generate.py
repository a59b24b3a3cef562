"""``regnf generate``: deterministic per seed, resumable, failures recorded, Ray equal to local.

A stage of tiny neural fields (two chairs and a table registered in a blob of a room; the
library holds a third chair) is generated into data sets of a few 24 x 18 views. The truths
are independent of the generation code: the replacement layers as USD reads them, the
in-process single-variant path (:func:`regnf.compositor.replace.replace_and_render`) rendering
the same seed from the same cameras, and a run that was never interrupted.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf

from regnf.cli.app import main
from regnf.compositor.baked_composite import masked_scene
from regnf.compositor.cameras_io import OrbitConfig, field_bounds_metres
from regnf.compositor.from_stage import composite_from_stage
from regnf.compositor.render_folder import RenderConfig
from regnf.compositor.replace import ReplaceConfig, pick_replacements, replace_and_render
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.atomic_io import TEMP_PREFIX
from regnf.core.executors import ExecutorConfig
from regnf.core.file_lock import LOCK_NAME
from regnf.core.image_io import read_depth_png, read_instance_png, read_rgb_png
from regnf.datasets.generation import GenerateConfig, generate, prepare_output, variant_cameras
from regnf.datasets.manifest import MANIFEST_NAME, load_rows
from regnf.scene_graph import add_instance, read_stage
from regnf.scene_graph import layout as L
from tests.scene_graph.helpers import make_stage, similarity

ROOT = Path(__file__).resolve().parents[2]
N = 6
"""Variants of the reference data set."""
ORBIT = OrbitConfig(n=3, width=24, height=18, radius=4.5)
"""Cameras well outside the tiny scene blob."""
CLI_VIEWS = ["--cameras.n", "3", "--cameras.width", "24", "--cameras.height", "18", "--cameras.radius", "4.5"]
"""The same cameras on the command line."""


def config(n: int = N, kind: str = "local", workers: int = 2) -> GenerateConfig:
    return GenerateConfig(variants=n, cameras=ORBIT, executor=ExecutorConfig(kind=kind, workers=workers))


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = make_stage(tmp_path_factory.mktemp("generate"), names=("c", "dc", "fc", "fc-nop", "t"))
    add_instance(path, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(path, "dc", similarity(1.5, (-2.2, 0.4, 0.0), 1.0))
    add_instance(path, "t", similarity(-0.3, (0.3, 2.3, 0.0), 1.0))
    return path


@pytest.fixture(scope="module")
def reference(stage: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An uninterrupted local run of N variants."""
    out = tmp_path_factory.mktemp("reference") / "data"
    report = generate(stage, out, config(), progress=False)
    assert report.made == list(range(N)) and not report.failed and not report.problems
    return out


def tree(out: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file of a data set, render.json (it holds timings) and the
    lock files (they name the last holder's pid) aside."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name not in ("render.json", LOCK_NAME)}


def assert_same_images(a: Path, b: Path, views: int) -> None:
    """RGB within one 8-bit level, depth and instance masks equal, view by view."""
    for k in range(views):
        ra, rb = (read_rgb_png(d / f"rgb_{k:04d}.png").astype(int) for d in (a, b))
        assert np.abs(ra - rb).max() <= 1, f"view {k}"
        assert np.array_equal(read_depth_png(a / f"depth_{k:04d}.png"), read_depth_png(b / f"depth_{k:04d}.png"))
        assert np.array_equal(read_instance_png(a / f"instance_{k:04d}.png"),
                              read_instance_png(b / f"instance_{k:04d}.png"))


def test_every_variant_is_its_seed_s_replacement(stage: Path, reference: Path, tmp_path: Path) -> None:
    rows = load_rows(reference)
    assert [r["seed"] for r in rows] == list(range(N)) and {r["status"] for r in rows} == {"ok"}
    scene = read_stage(stage)
    chosen = set()
    for r in rows:
        # The layer, read back by USD, shows the row's selections; they are the seed's choices.
        layered = read_stage(reference / r["layer"])
        assert {i: inst.library_name for i, inst in layered.instances.items()} == r["selections"]
        assert r["selections"] == pick_replacements(scene, r["seed"])
        chosen.add(tuple(sorted(r["selections"].items())))
        folder = reference / r["variant"]
        assert r["views"] == 3 and (folder / "contact_sheet.png").is_file() and (folder / "render.json").is_file()
        tj = json.loads((folder / "transforms.json").read_text())
        assert [f["file_path"] for f in tj["frames"]] == [f"rgb_{k:04d}.png" for k in range(3)]
        assert (folder / tj["regnf"]["stage"]).resolve() == (reference / r["layer"]).resolve()
        ids = set(np.unique(np.concatenate([read_instance_png(folder / f"instance_{k:04d}.png").ravel()
                                            for k in range(3)])))
        # 0 background and the room, k instance k.
        assert ids <= {0, *r["instance_ids"].values()} and len(ids) >= 3
    assert len(chosen) >= 2, "every seed chose the same objects"

    # The same seed through the single-variant path, in this process, from the same cameras.
    seed = 4
    bounds = field_bounds_metres(composite_from_stage(stage, StageCompositeConfig(mode="scene")).field.scene)
    cams = variant_cameras(bounds, config(), seed)
    result = replace_and_render(stage, seed, tmp_path / "one", cams, ReplaceConfig())
    assert result.selections == rows[seed]["selections"]
    assert_same_images(tmp_path / "one", reference / rows[seed]["variant"], 3)


def test_ray_gives_the_local_outputs(stage: Path, reference: Path, tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        report = generate(stage, tmp_path / "ray", config(kind="ray"), progress=False)
    finally:
        ray.shutdown()
    assert report.made == list(range(N)) and not report.failed
    assert (tmp_path / "ray" / MANIFEST_NAME).read_text() == (reference / MANIFEST_NAME).read_text()
    for r in load_rows(reference):
        assert_same_images(tmp_path / "ray" / r["variant"], reference / r["variant"], 3)


def test_a_killed_run_resumes_to_the_uninterrupted_outputs(stage: Path, reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    cmd = [sys.executable, "-m", "regnf", "generate", str(stage), "--out", str(out), "--variants", str(N),
           "--executor.workers", "1", *CLI_VIEWS]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    manifest = out / MANIFEST_NAME
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if manifest.is_file() and manifest.read_text().count("\n") >= 1:
            break
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()[-2000:]}"
    os.killpg(proc.pid, signal.SIGKILL)  # the driver and its workers, at once
    proc.wait()
    proc.stderr.close()
    kept = load_rows(out)
    assert 1 <= len(kept) < N
    # What else a kill can leave: a staging folder, and a finished-looking folder with no row.
    missing = max(set(range(N)) - {r["seed"] for r in kept})
    half = out / "variants" / f"{TEMP_PREFIX}{missing:06d}-half"
    half.mkdir(parents=True)
    (half / "rgb_0000.png").write_bytes(b"half")
    shutil.copytree(out / kept[0]["variant"], out / "variants" / f"{missing:06d}", dirs_exist_ok=True)

    report = generate(stage, out, config(), progress=False)
    assert report.skipped == sorted(r["seed"] for r in kept)
    assert sorted(report.made) == sorted(set(range(N)) - set(report.skipped))
    assert tree(out) == tree(reference)


def test_damaged_rows_and_files_are_detected_and_redone(stage: Path, reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    lines = (out / MANIFEST_NAME).read_text().splitlines()
    edited = json.loads(lines[1])
    edited["selections"] = {k: "c" for k in edited["selections"]}  # valid JSON, wrong content
    lines[1] = json.dumps(edited, sort_keys=True)
    lines[3] = lines[3][: len(lines[3]) // 2]  # a torn line
    (out / MANIFEST_NAME).write_text("\n".join(lines) + "\n")
    png = out / load_rows(reference)[5]["variant"] / "depth_0001.png"
    png.write_bytes(png.read_bytes()[:-7])  # a damaged file under a good row

    report = generate(stage, out, config(), progress=False)
    assert sorted(report.made) == [1, 3, 5] and report.skipped == [0, 2, 4]
    assert len(report.problems) == 3
    assert "row_sha256" in report.problems[0] and "not JSON" in report.problems[1]
    assert "depth_0001.png differs" in report.problems[2]
    assert tree(out) == tree(reference)
    # A rerun of a complete data set does nothing.
    again = generate(stage, out, config(), progress=False)
    assert again.made == [] and again.skipped == list(range(N)) and again.problems == []


def test_a_failed_variant_is_recorded_and_the_others_finish(stage: Path, reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    cfg = config()
    base, _ = prepare_output(stage, out, cfg)
    # Damage one library object only: its layer's to_world no longer matches its checkpoint.
    layer = Sdf.Layer.FindOrOpen(str(base.parent / L.library_layer("fc-nop")))
    prim = layer.GetPrimAtPath(layer.defaultPrim)
    attr = prim.attributes[L.A_TO_WORLD]
    M = attr.default
    attr.default = Gf.Matrix4d(*[M[i][j] * (1.5 if i == j and i < 3 else 1.0) for i in range(4) for j in range(4)])
    layer.Save()
    uses_nop = {r["seed"] for r in load_rows(reference) if "fc-nop" in r["selections"].values()}
    assert uses_nop and uses_nop != set(range(N))

    assert main(["generate", str(stage), "--out", str(out), "--variants", str(N), *CLI_VIEWS]) == 4
    rows = {r["seed"]: r for r in load_rows(out)}
    assert {s for s, r in rows.items() if r["status"] == "failed"} == uses_nop
    for s in uses_nop:
        assert "to_world" in rows[s]["error"]
        assert "Traceback" in (out / "errors" / f"{s:06d}.txt").read_text()
    good = {r["seed"]: r for r in load_rows(reference)}
    for s in set(range(N)) - uses_nop:
        assert rows[s] == good[s]


def test_other_settings_in_the_same_folder_are_refused(stage: Path, reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    shutil.copytree(reference, out)
    other = GenerateConfig(variants=N, cameras=OrbitConfig(n=3, width=32, height=18, radius=4.5))
    with pytest.raises(ValueError, match="generation.json.*other settings"):
        generate(stage, out, other, progress=False)


def test_a_package_is_unpacked_once_and_gives_the_same_variants(stage: Path, reference: Path,
                                                                 tmp_path: Path) -> None:
    from regnf.scene_graph import export_stage

    package = export_stage(stage, tmp_path / "scene.usdz")
    out = tmp_path / "data"
    report = generate(package, out, config(n=2), progress=False)
    assert report.made == [0, 1]
    assert (out / "stage" / "scene.usda").is_file()
    ref = {r["seed"]: r for r in load_rows(reference)}
    for r in load_rows(out):
        assert r["selections"] == ref[r["seed"]]["selections"]
        assert_same_images(out / r["variant"], reference / r["variant"], 3)


def baked_config(n: int = N) -> GenerateConfig:
    return dataclasses.replace(config(n), render=RenderConfig(renderer="baked", progress=False))


@pytest.fixture(scope="module")
def baked_reference(stage: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An uninterrupted local run of N variants with the baked renderer."""
    out = tmp_path_factory.mktemp("baked") / "data"
    report = generate(stage, out, baked_config(), progress=False)
    assert report.made == list(range(N)) and not report.failed and report.bake_seconds > 0
    return out


def test_the_baked_renderer_draws_each_variant_of_the_neural_fields(stage: Path, reference: Path,
                                                                    baked_reference: Path) -> None:
    """Against the neural render of the same seeds from the same cameras (the reference)."""
    index = json.loads((baked_reference / "baked" / "index.json").read_text())
    # Every object a variant may show (each chair's others; the table is the only table).
    assert sorted(index["objects"]) == ["c", "dc", "fc", "fc-nop", "t"]
    for r, b in zip(load_rows(reference), load_rows(baked_reference), strict=True):
        assert b["selections"] == r["selections"] and b["instance_ids"] == r["instance_ids"]
        for k in range(3):
            ids = [read_instance_png(d / f"instance_{k:04d}.png") for d in (reference / r["variant"],
                                                                         baked_reference / b["variant"])]
            same = ids[0] == ids[1]
            # 24 x 18 pixels: one is 0.23 %; the disagreements are silhouette pixels (12-13 at most).
            assert same.mean() >= 0.965, (r["seed"], k)
            rgb = [read_rgb_png(d / f"rgb_{k:04d}.png").astype(float) for d in (reference / r["variant"],
                                                                                baked_reference / b["variant"])]
            assert np.abs(rgb[0] - rgb[1])[same].mean() < 6.0, (r["seed"], k)
        assert json.loads((baked_reference / b["variant"] / "render.json").read_text())["renderer"] == "baked"


def test_one_replacement_on_the_data_set_s_grids_is_its_baked_variant(stage: Path, baked_reference: Path,
                                                                       tmp_path: Path) -> None:
    """The single-variant path given the grids (as the demo renders its replacements) draws the
    seed's variant of the baked data set, and refuses grids without an object the seed picks
    before it writes anything."""
    from regnf.datasets.data_set_grids import load_data_set_grids

    grids = load_data_set_grids(baked_reference / "baked" / "index.json")
    rows = {r["seed"]: r for r in load_rows(baked_reference)}
    seed = 4
    bounds = field_bounds_metres(composite_from_stage(stage, StageCompositeConfig(mode="scene")).field.scene)
    cams = variant_cameras(bounds, config(), seed)
    result = replace_and_render(stage, seed, tmp_path / "one", cams, ReplaceConfig(), grids=grids)
    assert result.selections == rows[seed]["selections"]
    record = json.loads((tmp_path / "one" / "render.json").read_text())
    assert record["renderer"] == "baked" and record["timings"]["bake_seconds"] == 0.0  # read, not baked
    assert_same_images(tmp_path / "one", baked_reference / rows[seed]["variant"], 3)

    shown = sorted(set(rows[seed]["selections"].values()))
    partial = grids._replace(objects={n: g for n, g in grids.objects.items() if n != shown[0]})
    with pytest.raises(ValueError, match=f"hold no .*{shown[0]}"):
        replace_and_render(stage, seed, tmp_path / "two", cams, ReplaceConfig(), grids=partial)
    assert not (tmp_path / "two").exists()


def test_each_variant_reads_the_grid_of_the_object_it_shows(stage: Path, baked_reference: Path) -> None:
    """The grids a worker puts in place: each baked from the object the instance shows (named by
    its checkpoint), and the composite's distances near the objects within a few cells of the
    neural composite's."""
    import torch

    from regnf.compositor.baked_composite import with_object_grids
    from regnf.compositor.from_stage import composite_from_scene
    from regnf.compositor.replace import swapped
    from regnf.datasets.data_set_grids import load_data_set_grids
    from regnf.scene_graph import original_selections

    grids = load_data_set_grids(baked_reference / "baked" / "index.json")
    scene = read_stage(stage)
    originals = original_selections(stage, scene)
    for r in load_rows(baked_reference)[:3]:
        comp = composite_from_scene(swapped(scene, r["selections"]), originals, stage,
                                    StageCompositeConfig(mode="substitute"))
        baked = with_object_grids(comp, r["selections"], grids)
        for iid, k in comp.instance_ids.items():
            placed = baked.placements[baked.instance_ids.index(k)]
            assert placed.field.info.name == r["selections"][iid]
            box = comp.field.placements[comp.field.instance_ids.index(k)].aabb().float()
            x = box[0] + torch.rand(4000, 3, generator=torch.Generator().manual_seed(k)) * (box[1] - box[0])
            # Against the composite with its scene evaluated everywhere (masked_scene): culled
            # by the removal regions, it is exact only within cull_pad (0.02) of a surface, and
            # this band is wider. The library fields stay culled to their boxes: a network says
            # nothing true outside its bounds.
            with torch.no_grad():
                exact = masked_scene(comp.field).sdf(x)
                for p in comp.field.placements:
                    exact = torch.minimum(exact, p.evaluate(x).sdf)
                approx = baked.sdf(x)
            near = exact.abs() < 0.05
            cell = max(float(g.info.provenance["baked"]["cell"]) * g_scale
                       for g, g_scale in ((placed.field, placed.scale), (grids.scene, 1.0)))
            assert near.sum() > 50 and float((exact - approx)[near].abs().max()) < 2 * cell


def test_the_grids_are_baked_once_and_a_resumed_run_equals_an_uninterrupted_one(
        stage: Path, baked_reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    first = generate(stage, out, baked_config(2), progress=False)
    assert first.made == [0, 1] and first.bake_seconds > 0
    grids = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (out / "baked").iterdir()}
    rest = generate(stage, out, baked_config(), progress=False)
    assert rest.skipped == [0, 1] and rest.made == list(range(2, N)) and rest.bake_seconds == 0.0
    assert {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in (out / "baked").iterdir()} == grids
    # The same bits as the uninterrupted run: the grids (one CPU thread per field) and every variant.
    assert tree(out) == tree(baked_reference)

    # A damaged grid is found by its digest and baked again, to the same bits.
    damaged = out / "baked" / "object_1.safetensors"
    data = bytearray(damaged.read_bytes())
    data[-5] ^= 0xFF
    damaged.write_bytes(bytes(data))
    more = generate(stage, out, baked_config(N + 1), progress=False)
    assert more.made == [N] and more.bake_seconds > 0
    assert damaged.read_bytes() == (baked_reference / "baked" / "object_1.safetensors").read_bytes()


def test_help_lists_every_generation_setting_with_its_documentation(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    from regnf.datasets.generation import GenerateConfig
    from tests.cli.cli_help import assert_documented, help_text, leaf_settings

    text = help_text("generate", capsys, monkeypatch)
    settings = leaf_settings(GenerateConfig, "--")
    assert len(settings) > 50  # cameras, composite, renderers, executor, the rest
    assert_documented(settings, text)
