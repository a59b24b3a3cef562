"""The data set formats a ``regnf generate`` run joins at its end, from its finished variants.

COCO (:func:`write_coco`): every variant's piece joined into ``coco/annotations.json``. BOP
(:func:`write_bop`): the models, and a scene for each variant made in the run or not yet in
``bop/``. Each variant's own files (views, class images, whole-silhouette masks, COCO piece)
are written by its worker (:mod:`regnf.variant_labels`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from regnf.compositor.render_folder import RENDER_JSON
from regnf.core.output_dir import remove_leftovers, replace_entry, staging_dir
from regnf.core.preflight import read_json_input

from .variant_labels import full_mask_file


def _variant_name(seed: int) -> str:
    """Folder name of a variant (:func:`regnf.generate.variant_name`)."""
    from .generate import variant_name

    return variant_name(seed)


def write_coco(out: Path, rows: dict[int, dict[str, Any]], views: int, source: dict[str, Any]) -> Path:
    """Join the COCO pieces of the finished variants (seed order) into ``coco/annotations.json``."""
    from . import coco

    cats = coco.categories(source["library"].values())
    pieces = ((s, json.loads((out / rows[s]["variant"] / coco.PIECE_NAME).read_text()))
              for s in sorted(rows) if rows[s]["status"] == "ok")
    return coco.write_annotations(out, coco.join_pieces(pieces, views, cats, f"regnf generate: {out.name}"))


def write_bop(out: Path, base: Path, rows: dict[int, dict[str, Any]], made: set[int],
              source: dict[str, Any]) -> list[str]:
    """Write the BOP layout (:mod:`regnf.bop`): the models, and a scene for each finished variant
    made in this run or not yet in ``bop/``; return the notes to show."""

    from regnf.scene_graph import read_stage

    from . import bop

    scene = read_stage(base)
    instances = {i: (r.library_name, np.asarray(r.object_to_scene, dtype=np.float64))
                 for i, r in scene.instances.items()}
    keys = bop.model_keys(source["library"], instances)
    obj_id = {key: k + 1 for k, key in enumerate(keys)}
    meshes = {name: model_mesh(rec) for name, rec in scene.library.items()}
    root = out / bop.BOP_DIR
    bop.write_models(root, keys, meshes, {n: r.symmetry_order for n, r in scene.library.items()})
    split = root / bop.SPLIT
    split.mkdir(parents=True, exist_ok=True)
    remove_leftovers(split)
    for seed in sorted(rows):  # a loop over variants
        row = rows[seed]
        final = split / _variant_name(seed)
        if row["status"] != "ok" or (final.is_dir() and seed not in made):
            continue
        cams = read_json_input(out / row["variant"] / RENDER_JSON, None, "render record")["cameras"]
        if not (root / "camera.json").is_file():
            bop.write_camera(root, cams[0])
        gts = []
        for name, iid in sorted(row["instance_ids"].items(), key=lambda kv: kv[1]):  # a loop over instances
            lib, matrix = row["selections"][name], instances[name][1]
            if name in row.get("placement", {}):  # a placement jitter: the pose shown
                matrix = np.asarray(row["placement"][name]["object_to_scene"], dtype=np.float64)
            _, centre = bop.model_frame(meshes[lib].vertices, 1.0)
            gts.append((int(iid), obj_id[bop.ModelKey(lib, round(bop.similarity_scale(matrix), bop.SCALE_DECIMALS))],
                        matrix, centre))
        masks = (read_full_mask(out / row["variant"] / full_mask_file(k, iid))
                 for k in range(len(cams)) for iid, *_ in gts)
        with staging_dir(split, _variant_name(seed)) as staging:
            bop.write_scene(staging, out / row["variant"], cams, gts, masks)
            replace_entry(staging, final)  # an earlier scene of this seed goes aside, then away
    fallback = sorted(n for n in {k.library_name for k in keys} if scene.library[n].source_mesh is None)
    if not fallback:
        return []
    return [(f"BOP models of {', '.join(fallback)} are their fields' meshes as the stage holds them "
            "(no source mesh: not distilled from a mesh)")]


def model_mesh(rec: Any) -> Any:
    """A library object's BOP model: its source mesh (its colours per vertex, a face's colour on
    corners of its own; a texture sampled at the vertices), else its field's mesh from the stage."""
    import trimesh

    src = rec.source_mesh
    if src is None:
        colors = rec.proxy.colors
        return trimesh.Trimesh(rec.proxy.points, rec.proxy.faces, process=False,
                               vertex_colors=None if colors is None
                               else np.round(255 * np.clip(colors, 0, 1)).astype(np.uint8))
    if src.face_colors is not None:
        # One vertex per face corner, so that each face keeps its own colour.
        corners = np.asarray(src.points, np.float64)[np.asarray(src.faces).reshape(-1)]
        rgb = np.repeat(np.round(255 * np.asarray(src.face_colors)).astype(np.uint8), 3, axis=0)
        return trimesh.Trimesh(corners, np.arange(len(corners)).reshape(-1, 3), process=False,
                               vertex_colors=np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1))
    mesh = trimesh.Trimesh(src.points, src.faces, process=False)
    if src.texture is not None:
        import io

        from PIL import Image

        with Image.open(io.BytesIO(src.texture)) as im:
            visual = trimesh.visual.TextureVisuals(uv=src.uv, image=im.convert("RGB"))
            mesh.visual = visual.to_color()
    else:
        mesh.visual.vertex_colors = np.append(np.round(255 * np.asarray(src.base_color)), 255).astype(np.uint8)
    return mesh


def read_full_mask(path: Path) -> np.ndarray:
    """(h, w) bool whole silhouette written by :func:`regnf.variant_labels.write_full_masks`."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im) > 127
