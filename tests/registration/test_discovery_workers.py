"""Discovery side by side in worker processes: the same result, bit for bit, as one candidate
after another in this process; a checkpoint changed under it is refused.

The fields are tiny ones distilled from meshes here (workers load checkpoints, so analytic
fields will not do): a floor with two poufs and a crate, and a library of the pouf and the
crate.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from regnf.fields.field import FieldInfo
from regnf.fields.neural_sdf import NeuralSDFConfig
from regnf.io.checkpoint import load_field, save_field
from regnf.registration.candidates import CandidateConfig
from regnf.registration.discovery import DiscoveryConfig, FieldFiles, discover
from regnf.training.distill import DistillConfig, distill_mesh

from ..compositor.golden_scenes import pouf_mesh

ARCH = NeuralSDFConfig(levels=4, features_per_level=2, base_resolution=8, finest_resolution=48,
                       hidden_dim=32, geo_feature_dim=4, color_hidden_dim=16)


def _crate() -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=(0.5, 0.35, 0.3))
    mesh.apply_translation((0.0, 0.0, 0.15))
    mesh.visual.face_colors = np.tile([[60, 120, 200, 255]], (len(mesh.faces), 1)).astype(np.uint8)
    return mesh


def _room() -> trimesh.Trimesh:
    floor = trimesh.creation.box(extents=(3.0, 3.0, 0.05))
    floor.apply_translation((0.0, 0.0, -0.025))
    floor.visual.face_colors = np.tile([[150, 150, 150, 255]], (len(floor.faces), 1)).astype(np.uint8)
    parts = [floor]
    for xy, yaw, mesh in (((0.7, 0.6), 0.0, pouf_mesh()), ((-0.8, -0.5), 0.0, pouf_mesh()),
                          ((0.6, -0.8), 0.6, _crate())):
        m = mesh.copy()
        m.apply_transform(trimesh.transformations.rotation_matrix(yaw, (0, 0, 1)))
        m.apply_translation((*xy, 0.0))
        parts.append(m)
    return trimesh.util.concatenate(parts)


def _distil(mesh: trimesh.Trimesh, name: str, label: str, steps: int) -> torch.nn.Module:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the same weights on any machine
    try:
        cfg = DistillConfig(steps=steps, batch=2048, pool_surface=20000, seed=0, architecture=ARCH)
        field, _ = distill_mesh(mesh, cfg, info=FieldInfo(label=label, name=name), progress=False)
    finally:
        torch.set_num_threads(threads)
    return field


@pytest.fixture(scope="module")
def fields(tmp_path_factory: pytest.TempPathFactory) -> FieldFiles:
    folder = tmp_path_factory.mktemp("discovery_workers")
    made = {"room": _distil(_room(), "room", "scene", 600), "pouf": _distil(pouf_mesh(), "pouf", "chair", 300),
            "crate": _distil(_crate(), "crate", "table", 300)}
    paths = {}
    for name, field in made.items():
        paths[name] = folder / f"{name}.safetensors"
        save_field(field, paths[name])
    return FieldFiles(paths["room"], {"pouf": paths["pouf"], "crate": paths["crate"]})


CONFIG = DiscoveryConfig(candidates=CandidateConfig(resolution=128), shortlist=2)


def _loaded(files: FieldFiles) -> tuple:
    return load_field(files.scene), {n: load_field(p) for n, p in files.library.items()}


def _same(a, b) -> None:
    assert len(a.discoveries) == len(b.discoveries)
    for x, y in zip(a.discoveries, b.discoveries, strict=True):
        assert np.array_equal(x.candidate.box.center, y.candidate.box.center)
        assert [(t.library_name, t.screened) for t in x.tried] == [(t.library_name, t.screened) for t in y.tried]
        for tx, ty in zip(x.tried, y.tried, strict=True):
            assert (tx.result is None) == (ty.result is None)
            if tx.result is not None:
                assert np.array_equal(tx.result.transform.matrix(), ty.result.transform.matrix())
                assert tx.result.confidence == ty.result.confidence
        assert (x.chosen is None) == (y.chosen is None) and x.ambiguous == y.ambiguous
        if x.chosen is not None:
            assert x.chosen.library_name == y.chosen.library_name
            assert np.array_equal(x.chosen.result.transform.matrix(), y.chosen.result.transform.matrix())


def test_workers_give_the_bits_of_one_candidate_after_another(fields: FieldFiles) -> None:
    scene, library = _loaded(fields)
    alone = discover(scene, library, dataclasses.replace(CONFIG, workers=1), files=fields)
    side_by_side = discover(scene, library, dataclasses.replace(CONFIG, workers=2), files=fields)
    # Not vacuous: several candidates, so the workers shared them, and objects were found.
    assert len(alone.discoveries) >= 3
    assert {d.chosen.library_name for d in alone.instances} == {"pouf", "crate"}
    _same(alone, side_by_side)


def test_a_checkpoint_changed_under_discovery_is_refused(fields: FieldFiles, tmp_path: Path) -> None:
    other = tmp_path / "crate.safetensors"
    # Another field under the crate's name: the workers would load it, not the crate given here.
    save_field(load_field(fields.library["pouf"]), other)
    files = FieldFiles(fields.scene, {**fields.library, "crate": other})

    from regnf.registration import discovery_workers

    workers = discovery_workers.DiscoveryWorkers(files, "cpu", dataclasses.replace(CONFIG, workers=2), 2)
    save_field(load_field(fields.library["crate"]), other)  # changed after discovery began
    with workers, pytest.raises(ValueError, match="changed since discovery began") as refused:
        workers.library_samples()
    assert "\n" not in str(refused.value)  # one line, no worker traceback


def test_files_must_name_the_library(fields: FieldFiles) -> None:
    scene, library = _loaded(fields)
    with pytest.raises(ValueError, match="files name the library objects"):
        discover(scene, library, CONFIG, files=FieldFiles(fields.scene, {"pouf": fields.library["pouf"]}))


def test_a_candidate_over_empty_space_is_skipped_in_a_worker_as_here(fields: FieldFiles) -> None:
    from regnf.fields.oriented_box import OrientedBox
    from regnf.registration import discovery_workers
    from regnf.registration.candidates import Candidate
    from regnf.registration.discovery import examine

    scene, library = _loaded(fields)
    # Air above the floor, away from every object: the scene's sampling finds no surface there.
    empty = Candidate(OrientedBox.from_aabb(np.array([-1.2, 0.8, 1.0]), np.array([-0.8, 1.2, 1.4])),
                      np.zeros((0, 3)))
    cfg = dataclasses.replace(CONFIG, workers=1)
    with discovery_workers.DiscoveryWorkers(fields, "cpu", cfg, 1) as pool:
        samples = pool.library_samples()
        there, = pool.examine([empty], samples, lambda: None)
    here = examine(empty, scene, library, samples, cfg)
    for d in (there, here):
        assert d.chosen is None and d.tried == []
        assert d.skipped.startswith("ranking the library in its box: RegnfError: ")
        assert "contains no surface" in d.skipped
    assert there.skipped == here.skipped
