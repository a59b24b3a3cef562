"""COCO instance segmentation of a generated data set: run-length masks, boxes, categories.

Each variant's worker turns its instance images into annotations (:func:`view_annotations`)
and writes them to ``variants/<seed>/coco.json`` (:func:`variant_piece`); at the end of a
run the pieces of every finished variant are joined into ``coco/annotations.json``
(:func:`write_annotations`), in seed order. An image's ``file_name`` is relative to the data
set's folder (the image root to give a COCO reader). Image ids are ``seed * views + k + 1``,
so a variant's images keep their ids when other variants are added or made again.

Masks are COCO's compressed run-length encoding (``{"size": [h, w], "counts": str}``, column
major, the first run counting background pixels), as ``pycocotools.mask.encode`` writes it;
``bbox`` is ``[x, y, width, height]`` in pixels of the mask's extent, ``area`` its pixel count.
Categories are the library's classes, sorted by name, with ids 1..C.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from regnf.core.atomic_io import write_text
from regnf.core.errors import RegnfError

COCO_DIR = "coco"
"""Folder of the data set's COCO file."""
ANNOTATIONS_NAME = "annotations.json"
"""The data set's COCO file in :data:`COCO_DIR`."""
PIECE_NAME = "coco.json"
"""A variant's annotations, in its folder."""


def categories(labels: Iterable[str]) -> list[dict[str, Any]]:
    """COCO categories of the classes ``labels`` (sorted, unique; ids 1..C, ``scene`` left out)."""
    names = sorted({str(x) for x in labels} - {"scene"})
    return [{"id": k + 1, "name": name, "supercategory": "object"} for k, name in enumerate(names)]


def run_lengths(mask: np.ndarray) -> np.ndarray:
    """COCO's run lengths of a binary mask.

    Parameters
    ----------
    mask : (h, w) bool

    Returns
    -------
    (r,) int64
        Alternating runs of 0 and 1 over the pixels in column-major order, starting with a
        (possibly empty) run of 0.
    """
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    if flat.size == 0:
        return np.zeros(1, dtype=np.int64)
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.concatenate([[0], change, [flat.size]])).astype(np.int64)
    return np.concatenate([[0], runs]) if flat[0] else runs


def compress_counts(runs: Sequence[int]) -> str:
    """COCO's compressed string of run lengths (as ``pycocotools`` writes it).

    Each count from the fourth on is stored as its difference to the count two before; every
    value goes out in 5-bit groups, low first, each as one character ``48 + group``, with bit 6
    set while more groups follow (the last group's bit 5 is the sign).
    """
    out: list[str] = []
    for i, count in enumerate(runs):  # a loop over runs (two per column crossed), not pixels
        x = int(count) - (int(runs[i - 2]) if i > 2 else 0)
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = x != -1 if c & 0x10 else x != 0
            out.append(chr(48 + (c | 0x20 if more else c)))
    return "".join(out)


def encode_mask(mask: np.ndarray) -> dict[str, Any]:
    """COCO compressed RLE of ``mask`` (h, w) bool: ``{"size": [h, w], "counts": str}``."""
    h, w = np.shape(mask)
    return {"size": [int(h), int(w)], "counts": compress_counts(run_lengths(mask))}


def mask_bbox(mask: np.ndarray) -> list[float]:
    """``[x, y, width, height]`` of the pixels of ``mask`` (h, w) bool; zeros when empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return [0.0, 0.0, 0.0, 0.0]
    return [float(cols[0]), float(rows[0]), float(cols[-1] - cols[0] + 1), float(rows[-1] - rows[0] + 1)]


def view_annotations(instances: np.ndarray, category_of: Mapping[int, int],
                     names: Mapping[int, str]) -> list[dict[str, Any]]:
    """One annotation per instance seen in an instance image.

    Parameters
    ----------
    instances : (h, w) int
        Instance ids, 0 background (regnf's instance PNG).
    category_of : mapping int -> int
        Instance id -> COCO category id.
    names : mapping int -> str
        Instance id -> the stage's instance name.

    Returns
    -------
    list of dict
        ``instance_id``, ``instance``, ``category_id``, ``segmentation``, ``area``, ``bbox``,
        ``iscrowd`` (0), in increasing instance id.
    """
    out = []
    for iid in np.unique(instances):  # a loop over the instances seen
        iid = int(iid)
        if iid == 0:
            continue
        if iid not in category_of:
            raise RegnfError(f"instance id {iid} in the image has no category")
        mask = instances == iid
        out.append({"instance_id": iid, "instance": names[iid], "category_id": int(category_of[iid]),
                    "segmentation": encode_mask(mask), "area": int(mask.sum()),
                    "bbox": mask_bbox(mask), "iscrowd": 0})
    return out


def variant_piece(variant_folder: str, rgb_files: Sequence[str], sizes: Sequence[tuple[int, int]],
                  annotations: Sequence[list[dict[str, Any]]]) -> dict[str, Any]:
    """A variant's COCO piece: its images (paths relative to the data set) and their annotations.

    ``sizes`` are (width, height) per view; ``annotations[k]`` are view ``k``'s.
    """
    if not len(rgb_files) == len(sizes) == len(annotations):
        raise RegnfError("need one size and one annotation list per image")
    return {"images": [{"view": k, "file_name": f"{variant_folder}/{name}", "width": int(w), "height": int(h)}
                       for k, (name, (w, h)) in enumerate(zip(rgb_files, sizes, strict=True))],
            "annotations": [{"view": k, **a} for k, anns in enumerate(annotations) for a in anns]}


def join_pieces(pieces: Iterable[tuple[int, dict[str, Any]]], views: int,
                cats: list[dict[str, Any]], description: str) -> dict[str, Any]:
    """The data set's COCO file from ``(seed, piece)`` in seed order; ``views`` per variant."""
    images: list[dict[str, Any]] = []
    annotations: list[dict[str, Any]] = []
    for seed, piece in pieces:
        for image in piece["images"]:
            images.append({"id": seed * views + int(image["view"]) + 1, "seed": seed,
                           **{k: v for k, v in image.items()}})
        for ann in piece["annotations"]:
            annotations.append({"id": len(annotations) + 1, "image_id": seed * views + int(ann["view"]) + 1,
                                "seed": seed, **{k: v for k, v in ann.items() if k != "view"}})
    return {"info": {"description": description, "version": "1.0"}, "licenses": [],
            "categories": cats, "images": images, "annotations": annotations}


def write_annotations(out: str | os.PathLike, coco: Mapping[str, Any]) -> Path:
    """Write ``coco`` to ``out/coco/annotations.json`` (temporary file, then rename)."""
    path = Path(out) / COCO_DIR / ANNOTATIONS_NAME
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, json.dumps(coco, separators=(",", ":")) + "\n")
    return path
