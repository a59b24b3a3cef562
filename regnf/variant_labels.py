"""Labels of a generated variant beyond its views: class images, COCO annotations, 3D boxes.

From a variant's rendered folder (``instance_k.png``: instance ids, 0 background) and the
stage as the variant shows it, :func:`write_labels` adds per view ``class_k.png`` (16-bit
category id of the library class seen at each pixel, 0 background and the room, ids as in
:func:`regnf.coco.categories`) and, when COCO is asked for, the variant's COCO piece
(:data:`regnf.coco.PIECE_NAME`). :func:`instance_boxes` gives each instance's oriented 3D box
in room metres for the manifest.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from regnf.core.image_io import read_instance_png, write_instance_png
from regnf.neural_fields.oriented_box import OrientedBox

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
        raise ValueError(f"unknown data set format {', '.join(unknown) or repr(text)}: "
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
            raise ValueError(f"view {k} shows instance {int(ids.max())}, which the variant does not hold")
        write_instance_png(folder / class_file(k), lut[ids])
        if "coco" in formats:
            rgb.append(f"rgb_{k:04d}.png")
            sizes.append((ids.shape[1], ids.shape[0]))
            anns.append(coco.view_annotations(ids, category_of, names))
    if "coco" in formats:
        piece = coco.variant_piece(variant_folder, rgb, sizes, anns)
        (folder / coco.PIECE_NAME).write_text(json.dumps(piece, separators=(",", ":")) + "\n")


def full_mask_file(k: int, instance_id: int) -> str:
    """File name of instance ``instance_id``'s whole silhouette in view ``k`` (8-bit, 255 inside)."""
    return f"full_{k:04d}_{instance_id:04d}.png"


def write_full_masks(folder: Path, field: Any, cameras: Sequence[Any], sphere: Any) -> None:
    """Write every instance's whole silhouette in every view: its object traced alone.

    The view's own images decide most pixels: where the composite shows the instance, the
    object alone is hit too (the composite's first hit is its first); where the view shows no
    surface, nothing is hit. Only the other pixels of the object's projected box are traced,
    each from just before the surface the view shows there (the object lies behind it).

    Parameters
    ----------
    folder : Path
        The variant's folder, with its instance and depth images
        (:func:`regnf.compositor.render_folder.view_files`).
    field : CompositeField
        The variant's composite (neural or baked), in the scene field frame.
    cameras : sequence of Camera
        The variant's cameras, room metres.
    sphere : SphereTracerConfig
        The tracer settings the views were rendered with.
    """
    import torch
    from PIL import Image

    from regnf.compositor.render_folder import view_files
    from regnf.core.image_io import read_depth_png, read_instance_png
    from regnf.neural_fields.analytic import Transformed
    from regnf.neural_fields.camera import camera_rays
    from regnf.neural_fields.sphere_tracer import trace

    views = [(read_instance_png(folder / view_files(k).instance), read_depth_png(folder / view_files(k).depth))
             for k in range(len(cameras))]
    for placement, iid in zip(field.placements, field.instance_ids, strict=True):  # a loop over instances
        alone = Transformed(placement.mapped.child, placement.mapped.matrix, to_world=field.to_world)
        to_world = alone.to_world.detach().cpu().double().numpy()
        lo, hi = alone.bounds.detach().cpu().double().numpy()
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, 3)
        corners = corners @ to_world[:3, :3].T + to_world[:3, 3]
        masks, origins, dirs, starts, angles, where = [], [], [], [], [], []
        for k, (cam, (ids, depth)) in enumerate(zip(cameras, views, strict=True)):  # a loop over views
            masks.append(ids == int(iid))
            window = box_window(cam, corners)
            if window is None:
                continue
            x0, y0, x1, y1 = window
            rays = camera_rays(alone, crop_camera(cam, window))
            todo = ((ids[y0:y1, x0:x1] != int(iid)) & (depth[y0:y1, x0:x1] > 0)).reshape(-1)
            if not todo.any():
                continue
            pick = torch.as_tensor(np.flatnonzero(todo), device=rays.dirs.device)
            # Metres of z-depth to field units along the ray, less a margin for the depth's rounding.
            z = torch.as_tensor(depth[y0:y1, x0:x1].reshape(-1)[todo], dtype=rays.dirs.dtype, device=rays.dirs.device)
            starts.append(torch.clamp((z - FULL_MASK_MARGIN) / alone.world_scale / rays.z_scale[pick], min=0.0))
            origins.append(rays.origins[pick])
            dirs.append(rays.dirs[pick])
            angles.append(torch.full_like(starts[-1], rays.pixel_angle))
            rows, cols = np.divmod(np.flatnonzero(todo), x1 - x0)
            where.append((k, rows + y0, cols + x0))
        if origins:  # every view's undecided pixels in one trace
            # Few rays, each starting near its surface: a distance grid would cost more than it saves.
            plain = dataclasses.replace(sphere, grid_resolution=0)
            hits = trace(alone, torch.cat(origins), torch.cat(dirs), plain, None, torch.cat(angles), torch.cat(starts))
            hit = hits.hit.detach().cpu().numpy()
            first = 0
            for k, rows, cols in where:  # a loop over views
                masks[k][rows, cols] |= hit[first:first + len(rows)]
                first += len(rows)
        for k, mask in enumerate(masks):
            Image.fromarray(mask.astype(np.uint8) * 255).save(folder / full_mask_file(k, int(iid)), compress_level=1)


FULL_MASK_MARGIN = 0.005
"""How far before the surface a view shows a pixel's trace of a hidden object starts, metres
(depth images hold whole millimetres)."""


def box_window(camera: Any, corners: np.ndarray, near: float = 1e-3) -> tuple[int, int, int, int] | None:
    """The pixels ``(x0, y0, x1, y1)`` (end exclusive) that hold the projection of a box.

    Parameters
    ----------
    camera : Camera
    corners : (8, 3) float
        The box's corners, world metres.
    near : float
        A corner nearer the camera's plane than this (metres), or behind it: the whole image.

    Returns
    -------
    tuple of int, or None
        None when the box projects outside the image.
    """
    c2w = np.asarray(camera.camera_to_world, np.float64)
    local = (corners - c2w[:3, 3]) @ c2w[:3, :3]
    if (local[:, 2] <= near).any():
        return 0, 0, int(camera.width), int(camera.height)
    K = np.asarray(camera.K, np.float64)
    uv = local @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    # Pixel (u, v) is sampled at (u + 0.5, v + 0.5): a pixel of the window's border stays in.
    x0, y0 = np.floor(uv.min(axis=0) - 1.0).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0) + 1.0).astype(int)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, int(camera.width)), min(y1, int(camera.height))
    return (int(x0), int(y0), int(x1), int(y1)) if x1 > x0 and y1 > y0 else None


def crop_camera(camera: Any, window: tuple[int, int, int, int]) -> Any:
    """The camera of the pixels ``window`` of ``camera``'s image (same rays, principal point moved)."""
    x0, y0, x1, y1 = window
    K = np.asarray(camera.K, np.float64).copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return dataclasses.replace(camera, K=K, width=x1 - x0, height=y1 - y0)


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
