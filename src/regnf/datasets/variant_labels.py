"""Labels of a generated variant beyond its views: class images, COCO annotations, 3D boxes.

From a variant's rendered folder (``instance_k.png``: instance ids, 0 background) and the
stage as the variant shows it, :func:`write_labels` adds per view ``class_k.png`` (16-bit
category id of the library class seen at each pixel, 0 background and the room, ids as in
:func:`regnf.datasets.coco.categories`) and, when COCO is asked for, the variant's COCO piece
(:data:`regnf.datasets.coco.PIECE_NAME`). :func:`instance_boxes` gives each instance's oriented 3D box
in room metres for the manifest.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from regnf.core.errors import RegnfError
from regnf.core.image_io import read_instance_png, write_instance_png
from regnf.fields.oriented_box import OrientedBox

from . import coco

FORMATS = ("nerfstudio", "coco", "bop")
"""Data set formats ``regnf generate`` writes (``--format``, comma separated)."""


def parse_formats(text: str) -> tuple[str, ...]:
    """The formats named in ``text`` (comma separated; unique, in :data:`FORMATS` order).

    Raises ``ValueError`` naming an unknown format.
    """
    names = [t.strip() for t in str(text).split(",") if t.strip()]
    unknown = sorted(set(names) - set(FORMATS))
    if unknown or not names:
        raise RegnfError(f"unknown data set format {', '.join(unknown) or repr(text)}: "
                         f"choose one or more of {', '.join(FORMATS)}, comma separated")
    return tuple(f for f in FORMATS if f in names)


def class_file(k: int) -> str:
    """File name of view ``k``'s class image."""
    return f"class_{k:04d}.png"


def instance_categories(scene: Any, selections: Mapping[str, str], instance_ids: Mapping[str, int],
                        cats: Sequence[dict[str, Any]]) -> dict[int, int]:
    """Render instance id -> category id of the library object each instance shows."""
    cat_id = {c["name"]: c["id"] for c in cats}
    return {int(instance_ids[name]): cat_id[scene.library[lib].label] for name, lib in selections.items()}


def write_labels(folder: Path, views: int, scene: Any, selections: Mapping[str, str],
                 instance_ids: Mapping[str, int], variant_folder: str, formats: Sequence[str]) -> None:
    """Write the class images (and the COCO piece) of a rendered variant into ``folder``.

    Parameters
    ----------
    folder : Path
        The variant's rendered views (``rgb_k.png``, ``instance_k.png``).
    views : int
        Number of views.
    scene : ComposedScene
        The stage (its library gives the classes).
    selections : mapping str -> str
        Stage instance -> library object shown.
    instance_ids : mapping str -> int
        Stage instance -> id in the instance images.
    variant_folder : str
        The variant's folder relative to the data set (COCO file names).
    formats : sequence of str
        The data set's formats (:data:`FORMATS`).
    """
    cats = coco.categories(lib.label for lib in scene.library.values())
    category_of = instance_categories(scene, selections, instance_ids, cats)
    names = {int(i): name for name, i in instance_ids.items()}
    lut = np.zeros(max(category_of, default=0) + 1, dtype=np.int64)
    for iid, cid in category_of.items():  # a loop over instances
        lut[iid] = cid
    rgb, sizes, anns = [], [], []
    for k in range(views):  # a loop over views
        ids = read_instance_png(folder / f"instance_{k:04d}.png")
        if ids.max(initial=0) >= lut.size:
            raise RegnfError(f"view {k} shows instance {int(ids.max())}, which the variant does not hold")
        write_instance_png(folder / class_file(k), lut[ids])
        if "coco" in formats:
            rgb.append(f"rgb_{k:04d}.png")
            sizes.append((ids.shape[1], ids.shape[0]))
            anns.append(coco.view_annotations(ids, category_of, names))
    if "coco" in formats:
        piece = coco.variant_piece(variant_folder, rgb, sizes, anns)
        (folder / coco.PIECE_NAME).write_text(json.dumps(piece, separators=(",", ":")) + "\n")


def instance_boxes(scene: Any, selections: Mapping[str, str], instance_ids: Mapping[str, int]) -> dict[str, Any]:
    """Each instance's oriented 3D box in room metres, from the shown object's mesh extent.

    Returns
    -------
    dict
        Stage instance -> ``id`` (its instance image id), ``library_name``, ``class``,
        ``center`` (3,), ``half_extents`` (3,), ``rotation`` (3, 3) row-major, columns the box
        axes in room coordinates.
    """
    import torch

    out = {}
    for name, lib in sorted(selections.items()):  # a loop over instances
        record = scene.library[lib]
        extent = torch.from_numpy(record.proxy.extent.astype(np.float64))
        box = OrientedBox.from_bounds(extent, scene.instances[name].object_to_scene)
        out[name] = {"id": int(instance_ids[name]), "library_name": lib, "class": record.label,
                     "center": [float(v) for v in box.center],
                     "half_extents": [float(v) for v in box.half_extents],
                     "rotation": [[float(v) for v in row] for row in box.rotation]}
    return out
