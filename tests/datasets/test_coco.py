"""COCO output of ``regnf generate``: the masks as pycocotools reads them, against the instance images.

The encoder is checked against pycocotools' own on random and structured masks; a generated
data set's ``coco/annotations.json`` is loaded with pycocotools, and every decoded mask must
equal its view's instance image (read with PIL, not regnf's reader) pixel for pixel.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycocotools.mask as mask_api
import pytest
from PIL import Image
from pycocotools.coco import COCO

from regnf.compositor.cameras_io import OrbitConfig
from regnf.core.executors import ExecutorConfig
from regnf.datasets.coco import encode_mask, mask_bbox, run_lengths
from regnf.datasets.generation import GenerateConfig, generate
from regnf.scene_graph import add_instance
from tests.scene_graph.helpers import make_stage, similarity

ORBIT = OrbitConfig(n=3, width=24, height=18, radius=4.5)
"""Cameras well outside the tiny scene blob."""


def masks() -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    out = [np.zeros((5, 7), bool), np.ones((5, 7), bool), np.eye(6, dtype=bool)]
    for _ in range(60):
        h, w = rng.integers(1, 50, 2)
        out.append(rng.random((h, w)) < rng.random())
        block = np.zeros((h, w), bool)
        block[rng.integers(0, h):, rng.integers(0, w):] = True
        out.append(block)
    big = np.zeros((300, 400), bool)  # runs over 2^15: counts of several 5-bit groups
    big[:, 200:] = True
    return [*out, big]


def test_the_encoding_is_pycocotools_own() -> None:
    for m in masks():
        ours = encode_mask(m)
        ref = mask_api.encode(np.asfortranarray(m.astype(np.uint8)))
        assert ours["counts"] == ref["counts"].decode() and ours["size"] == list(m.shape)
        assert np.array_equal(mask_api.decode(ours), m)
        assert run_lengths(m).sum() == m.size
        if m.any():
            assert mask_bbox(m) == mask_api.toBbox(ours).tolist()
    assert mask_bbox(np.zeros((3, 3), bool)) == [0.0, 0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def data_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("coco")
    stage = make_stage(root, names=("c", "dc", "fc", "fc-nop", "t"))
    add_instance(stage, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(stage, "dc", similarity(1.5, (-2.2, 0.4, 0.0), 1.0))
    add_instance(stage, "t", similarity(-0.3, (0.3, 2.3, 0.0), 1.0))
    out = root / "data"
    cfg = GenerateConfig(format="coco,nerfstudio", variants=3, first_seed=2, cameras=ORBIT,
                         executor=ExecutorConfig(kind="local", workers=2))
    report = generate(stage, out, cfg, progress=False)
    assert report.made == [2, 3, 4] and not report.failed
    return out


def ids_of(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im).astype(np.int64)


def test_pycocotools_reads_every_instance_image_exactly(data_set: Path) -> None:
    coco = COCO(str(data_set / "coco" / "annotations.json"))
    rows = [json.loads(line) for line in (data_set / "manifest.jsonl").read_text().splitlines()]
    labels = {"c": "chair", "dc": "chair", "fc": "chair", "fc-nop": "chair", "t": "table"}
    assert sorted(c["name"] for c in coco.loadCats(coco.getCatIds())) == ["chair", "table"]
    assert len(coco.getImgIds()) == 3 * 3
    seen = 0
    for row in rows:
        names = {v: k for k, v in row["instance_ids"].items()}
        assert set(row["boxes"]) == set(row["instance_ids"])  # the 3D boxes (test_variant_labels.py)
        for k in range(3):
            image_id = row["seed"] * 3 + k + 1
            (img,) = coco.loadImgs([image_id])
            assert img["file_name"] == f"{row['variant']}/rgb_{k:04d}.png" and (data_set / img["file_name"]).is_file()
            ids = ids_of(data_set / row["variant"] / f"instance_{k:04d}.png")
            assert (img["height"], img["width"]) == ids.shape
            anns = coco.loadAnns(coco.getAnnIds(imgIds=[image_id]))
            assert sorted(a["instance_id"] for a in anns) == sorted(set(np.unique(ids).tolist()) - {0})
            for a in anns:
                assert np.array_equal(coco.annToMask(a).astype(bool), ids == a["instance_id"])
                assert a["area"] == int((ids == a["instance_id"]).sum())
                assert a["instance"] == names[a["instance_id"]]
                cat = coco.loadCats([a["category_id"]])[0]["name"]
                assert cat == labels[row["selections"][a["instance"]]]
                seen += 1
    assert seen >= 6, "too few instances in view to test anything"


def test_the_class_images_hold_each_instance_s_category(data_set: Path) -> None:
    coco = json.loads((data_set / "coco" / "annotations.json").read_text())
    cat_id = {c["name"]: c["id"] for c in coco["categories"]}
    labels = {"c": "chair", "dc": "chair", "fc": "chair", "fc-nop": "chair", "t": "table"}
    for line in (data_set / "manifest.jsonl").read_text().splitlines():
        row = json.loads(line)
        for k in range(3):
            ids = ids_of(data_set / row["variant"] / f"instance_{k:04d}.png")
            classes = ids_of(data_set / row["variant"] / f"class_{k:04d}.png")
            assert np.array_equal(classes == 0, ids == 0)
            for name, iid in row["instance_ids"].items():
                assert (classes[ids == iid] == cat_id[labels[row["selections"][name]]]).all()
