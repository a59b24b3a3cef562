"""The data set formats of ``regnf generate`` beyond each variant's own files.

COCO (:func:`write_coco`): every finished variant's piece joined into
``coco/annotations.json`` at the end of a run. BOP: the models, written before the variants
(:func:`write_bop_models`); each variant's scene, made in its worker from its views and its
objects' whole silhouettes (:func:`variant_bop_scene`) and put in place with the variant
(:func:`commit_bop_scene`). Each variant's own files (views, class images, COCO piece) are
written by its worker (:mod:`regnf.datasets.variant_labels`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from regnf.compositor.render_folder import RENDER_JSON
from regnf.core.errors import RegnfError
from regnf.core.output_dir import remove_leftovers, replace_entry, staging_dir
from regnf.core.preflight import read_json_input

from . import bop
from .generate_layout import variant_name


def write_coco(out: Path, rows: dict[int, dict[str, Any]], views: int, source: dict[str, Any]) -> Path:
    """Join the COCO pieces of the finished variants (seed order) into ``coco/annotations.json``."""
    from . import coco

    cats = coco.categories(source["library"].values())
    pieces = ((s, json.loads((out / rows[s]["variant"] / coco.PIECE_NAME).read_text()))
              for s in sorted(rows) if rows[s]["status"] == "ok")
    return coco.write_annotations(out, coco.join_pieces(pieces, views, cats, f"regnf generate: {out.name}"))


def bop_scene_folder(out: Path, seed: int) -> Path:
    """``bop/train/<seed>``: where a variant's BOP scene goes."""
    return out / bop.BOP_DIR / bop.SPLIT / variant_name(seed)


def write_bop_models(out: Path, base: Path, source: dict[str, Any]) -> tuple[bop.ModelPlan, list[str]]:
    """Write the BOP models of every object a variant of ``base`` may show; return their plan
    and the notes to show (a library object without a source mesh, said once)."""
    from regnf.scene_graph import read_stage

    scene = read_stage(base)
    instances = {i: (r.library_name, np.asarray(r.object_to_scene, dtype=np.float64))
                 for i, r in scene.instances.items()}
    keys = bop.model_keys(source["library"], instances)
    meshes = {name: model_mesh(rec) for name, rec in scene.library.items()}
    root = out / bop.BOP_DIR
    plan = bop.write_models(root, keys, meshes, {n: r.symmetry_order for n, r in scene.library.items()})
    split = root / bop.SPLIT
    split.mkdir(parents=True, exist_ok=True)
    remove_leftovers(split)
    fallback = sorted(n for n in {k.library_name for k in keys} if scene.library[n].source_mesh is None)
    if not fallback:
        return plan, []
    return plan, [(f"BOP models of {', '.join(fallback)} are their fields' meshes as the stage holds them "
                   "(no source mesh: not distilled from a mesh)")]


def variant_bop_scene(folder: Path, plan: bop.ModelPlan, selections: Mapping[str, str],
                      instance_ids: Mapping[str, int], poses: Mapping[str, np.ndarray],
                      masks: Mapping[int, Sequence[np.ndarray]]) -> dict[str, bytes]:
    """A rendered variant's BOP scene (made in its worker): relative path -> content.

    Parameters
    ----------
    folder : Path
        The variant's rendered views and ``render.json``.
    plan : ModelPlan
        The run's models (:func:`write_bop_models`).
    selections, instance_ids, poses : mapping
        Stage instance -> library object shown, id in the instance images, object_to_scene
        (4, 4) shown.
    masks : mapping int -> sequence of (h, w) bool
        Instance image id -> its whole silhouette in each view
        (:func:`regnf.datasets.full_masks.full_masks`).
    """
    cams = read_json_input(folder / RENDER_JSON, None, "render record")["cameras"]
    gts = bop.ground_truths(plan, instance_ids, selections, poses)
    return bop.scene_files(folder, cams, gts, (masks[iid][k] for k in range(len(cams)) for iid, *_ in gts))


def commit_bop_scene(out: Path, seed: int, files: Mapping[str, bytes], first_camera: Mapping[str, Any]) -> None:
    """Put a variant's BOP scene (:func:`variant_bop_scene`) in place: staging folder, then rename.

    ``bop/camera.json`` is written from ``first_camera`` (a ``render.json`` camera) if missing.
    """
    root = out / bop.BOP_DIR
    final = bop_scene_folder(out, seed)
    with staging_dir(final.parent, final.name) as staging:
        for rel, data in sorted(files.items()):
            parts = rel.split("/")
            if any(not p or p in (".", "..") or p.startswith(".") for p in parts):
                raise RegnfError(f"a worker returned a BOP file named {rel!r}, not a plain relative path")
            target = staging.joinpath(*parts)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        replace_entry(staging, final)  # an earlier scene of this seed goes aside, then away
    if not (root / "camera.json").is_file():
        bop.write_camera(root, first_camera)


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
