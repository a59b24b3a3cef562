"""BOP layout of a generated data set: object models, and one scene per variant with poses and masks.

Written under ``bop/`` in the data set's folder, in BOP's scene-wise format::

    bop/camera.json                       the orbit's intrinsics (for simulators; per image below)
    bop/models/obj_000001.ply ...         one model per object and scale, millimetres, normals
    bop/models/models_info.json           diameter, 3D box, symmetries of every model
    bop/train/000007/rgb/000000.png       seed 7's view 0 (a copy of variants/000007/rgb_0000.png)
    bop/train/000007/depth/000000.png     16-bit millimetres (depth_scale 1)
    bop/train/000007/mask/000000_000001.png       view 0, ground truth 1: the whole silhouette
    bop/train/000007/mask_visib/000000_000001.png  ...its visible part
    bop/train/000007/scene_camera.json    cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)
    bop/train/000007/scene_gt.json        per image: obj_id, cam_R_m2c, cam_t_m2c (mm) of every instance
    bop/train/000007/scene_gt_info.json   per image and instance: boxes, pixel counts, visible fraction

BOP poses are rigid and models are in millimetres, while an instance places its object by a
similarity: every (library object, instance scale) pair a variant may show gets a model of its
own, the object's mesh scaled by that factor, with its origin at the centre of its 3D box (as
BOP asks); ``models_info.json`` records each model's ``library_name`` and ``scale`` beside
BOP's keys. A model is its library object's source mesh when it was distilled from one, else
its field's mesh as the stage holds them. The models are written once per run, before the
variants; each variant's worker makes its scene (:func:`scene_files`), with the obj_ids of
the run's :class:`ModelPlan`.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from regnf.core.atomic_io import write_bytes, write_text

BOP_DIR = "bop"
"""Folder of the BOP layout in the data set."""
SPLIT = "train"
"""The split the variants' scenes go to."""
SCALE_DECIMALS = 6
"""Instance scales are told apart to this many decimals (one model per distinct value)."""


class ModelKey(NamedTuple):
    """What a BOP model is: a library object at an instance's scale."""

    library_name: str
    """The library object."""
    scale: float
    """Instance scale (canonical object metres -> room metres), rounded to SCALE_DECIMALS."""


class ModelPlan(NamedTuple):
    """The data set's BOP models as a variant's worker needs them (:func:`ground_truths`)."""

    obj_ids: dict[ModelKey, int]
    """Model -> its obj_id (1.., in :func:`model_keys` order)."""
    centres: dict[str, tuple[float, float, float]]
    """Library object -> the centre of its mesh's box, canonical metres (its models' origin)."""


def ground_truths(plan: ModelPlan, instance_ids: Mapping[str, int], selections: Mapping[str, str],
                  poses: Mapping[str, np.ndarray]) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """A variant's ground truths, in instance image id order (:func:`scene_files`' ``instances``).

    Parameters
    ----------
    plan : ModelPlan
    instance_ids : mapping str -> int
        Stage instance -> id in the instance images.
    selections : mapping str -> str
        Stage instance -> library object shown.
    poses : mapping str -> (4, 4) float
        Stage instance -> the object_to_scene it is shown at.
    """
    out = []
    for name, iid in sorted(instance_ids.items(), key=lambda kv: kv[1]):  # a loop over instances
        matrix = np.asarray(poses[name], dtype=np.float64)
        key = ModelKey(selections[name], round(similarity_scale(matrix), SCALE_DECIMALS))
        out.append((int(iid), plan.obj_ids[key], matrix, np.asarray(plan.centres[key.library_name], np.float64)))
    return out


def similarity_scale(matrix: np.ndarray) -> float:
    """Uniform scale of a (4, 4) similarity."""
    return float(np.cbrt(abs(np.linalg.det(np.asarray(matrix, dtype=np.float64)[:3, :3]))))


def model_keys(library_classes: Mapping[str, str], instances: Mapping[str, tuple[str, np.ndarray]]) -> list[ModelKey]:
    """Every model a variant may show, sorted (their obj_ids are 1.. in this order).

    Parameters
    ----------
    library_classes : mapping str -> str
        Library object -> class.
    instances : mapping str -> (str, (4, 4) float)
        Instance -> (its original library object, object_to_scene). A variant swaps each
        instance for any object of the same class.
    """
    keys = set()
    for original, matrix in instances.values():  # a loop over instances
        s = round(similarity_scale(matrix), SCALE_DECIMALS)
        for name, label in library_classes.items():
            if label == library_classes[original]:
                keys.add(ModelKey(name, s))
    return sorted(keys)


def model_frame(points: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The model's vertices (mm, origin at their box centre) and that centre (canonical metres).

    Parameters
    ----------
    points : (n, 3) float
        Mesh vertices, canonical object metres.
    scale : float
        Instance scale.

    Returns
    -------
    vertices : (n, 3) float64
        Millimetres in the model frame.
    centre : (3,) float64
        Centre of the vertices' box, canonical metres.
    """
    p = np.asarray(points, dtype=np.float64)
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    return 1000.0 * scale * (p - centre), centre


def diameter(vertices: np.ndarray) -> float:
    """Largest distance between two of the vertices (n, 3), over their convex hull's."""
    import trimesh

    v = np.asarray(vertices, dtype=np.float64)
    with contextlib.suppress(Exception):  # flat or degenerate: every vertex then
        v = trimesh.convex.convex_hull(v).vertices
    best = 0.0
    for first in range(0, len(v), 1024):  # chunks of rows keep the distance matrix small
        d = np.linalg.norm(v[first:first + 1024, None, :] - v[None, :, :], axis=-1)
        best = max(best, float(d.max(initial=0.0)))
    return best


def symmetries(order: int, axis_point: np.ndarray) -> dict[str, Any]:
    """BOP's symmetry entries of a rotational symmetry about +Z through ``axis_point`` (mm).

    ``order`` k > 1: the k - 1 discrete turns as row-major 4 x 4 matrices (mm); 0: continuous;
    1: none.
    """
    a = np.asarray(axis_point, dtype=np.float64)
    if order == 0:
        return {"symmetries_continuous": [{"axis": [0.0, 0.0, 1.0], "offset": a.tolist()}]}
    out = []
    for j in range(1, max(order, 1)):  # a loop over the turns
        c, s = math.cos(2 * math.pi * j / order), math.sin(2 * math.pi * j / order)
        T = np.eye(4)
        T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = a - T[:3, :3] @ a
        out.append(T.ravel().tolist())
    return {"symmetries_discrete": out} if out else {}


def write_models(bop: Path, keys: Sequence[ModelKey], meshes: Mapping[str, Any],
                 symmetry_orders: Mapping[str, int]) -> ModelPlan:
    """Write ``models/obj_*.ply`` and ``models_info.json`` for ``keys`` (obj_id k + 1); return their plan.

    ``meshes`` maps a library object to its mesh (a ``trimesh.Trimesh`` in canonical metres).
    """
    import trimesh

    folder = bop / "models"
    folder.mkdir(parents=True, exist_ok=True)
    info = {}
    for k, key in enumerate(keys):  # a loop over models
        mesh = meshes[key.library_name]
        vertices, centre = model_frame(mesh.vertices, key.scale)
        model = trimesh.Trimesh(vertices, np.asarray(mesh.faces), process=False)
        if getattr(mesh.visual, "kind", None) == "vertex":
            model.visual.vertex_colors = mesh.visual.vertex_colors
        model.vertex_normals  # noqa: B018 (computed so the PLY carries them)
        write_bytes(folder / f"obj_{k + 1:06d}.ply", trimesh.exchange.ply.export_ply(model, encoding="binary",
                                                                                       include_attributes=False,
                                                                                       vertex_normal=True))
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        entry = {"diameter": diameter(vertices), "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
                 "size_x": hi[0] - lo[0], "size_y": hi[1] - lo[1], "size_z": hi[2] - lo[2],
                 **symmetries(int(symmetry_orders[key.library_name]), -1000.0 * key.scale * centre),
                 "library_name": key.library_name, "scale": key.scale}
        info[str(k + 1)] = {n: (float(v) if isinstance(v, (float, np.floating)) else v) for n, v in entry.items()}
    write_text(folder / "models_info.json", json.dumps(info, indent=1) + "\n")
    centres = {name: tuple(float(v) for v in model_frame(mesh.vertices, 1.0)[1]) for name, mesh in meshes.items()}
    return ModelPlan({key: k + 1 for k, key in enumerate(keys)}, centres)


def model_to_camera(object_to_scene: np.ndarray, centre: np.ndarray, camera_to_world: np.ndarray) -> tuple[list, list]:
    """(cam_R_m2c row-major 9, cam_t_m2c mm 3) of a model whose box centre is ``centre``.

    Parameters
    ----------
    object_to_scene : (4, 4) float
        The instance's similarity (canonical metres -> room metres).
    centre : (3,) float
        The model's origin in canonical metres (:func:`model_frame`).
    camera_to_world : (4, 4) float
        OpenCV camera axes, metres.
    """
    M = np.asarray(object_to_scene, dtype=np.float64)
    s = similarity_scale(M)
    R = M[:3, :3] / s
    t = M[:3, :3] @ np.asarray(centre, dtype=np.float64) + M[:3, 3]  # the model origin in the room
    w2c = np.linalg.inv(np.asarray(camera_to_world, dtype=np.float64))
    return (w2c[:3, :3] @ R).ravel().tolist(), (1000.0 * (w2c[:3, :3] @ t + w2c[:3, 3])).tolist()


def box_of(mask: np.ndarray) -> list[int]:
    """``[x, y, width, height]`` of a mask (h, w) bool; ``[-1, -1, -1, -1]`` when empty (BOP's)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return [-1, -1, -1, -1]
    return [int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)]


def gt_info(full: np.ndarray, visible: np.ndarray, depth_mm: np.ndarray) -> dict[str, Any]:
    """BOP's ground-truth info of one instance in one image (masks (h, w) bool, depth (h, w))."""
    n_all, n_vis = int(full.sum()), int(visible.sum())
    return {"bbox_obj": box_of(full), "bbox_visib": box_of(visible), "px_count_all": n_all,
            "px_count_valid": int((full & (depth_mm > 0)).sum()), "px_count_visib": n_vis,
            "visib_fract": float(n_vis / n_all) if n_all else 0.0}


def scene_files(variant: Path, cameras: Sequence[Mapping[str, Any]],
                instances: Sequence[tuple[int, int, np.ndarray, np.ndarray]],
                masks: Iterable[np.ndarray]) -> dict[str, bytes]:
    """One variant as a BOP scene: path in the scene's folder (``bop/train/<seed>``) -> content.

    Parameters
    ----------
    variant : Path
        The variant's folder (``rgb_k.png``, ``depth_k.png``, ``instance_k.png``).
    cameras : sequence of mapping
        Per view ``K`` (3, 3) and ``camera_to_world`` (4, 4, OpenCV axes, metres), as in
        ``render.json``.
    instances : sequence of (int, int, (4, 4) float, (3,) float)
        Per ground truth: its instance image id, obj_id, object_to_scene and model centre.
    masks : iterable of (h, w) bool
        Whole silhouettes, view by view, in the order of ``instances``.
    """
    from PIL import Image

    from regnf.core.image_io import read_instance_png

    files: dict[str, bytes] = {}
    masks = iter(masks)
    scene_camera, scene_gt, scene_info = {}, {}, {}
    for k, cam in enumerate(cameras):  # a loop over views
        files[f"rgb/{k:06d}.png"] = (variant / f"rgb_{k:04d}.png").read_bytes()
        files[f"depth/{k:06d}.png"] = (variant / f"depth_{k:04d}.png").read_bytes()
        with Image.open(io.BytesIO(files[f"depth/{k:06d}.png"])) as im:
            depth = np.asarray(im).astype(np.int64)
        ids = read_instance_png(variant / f"instance_{k:04d}.png")
        c2w = np.asarray(cam["camera_to_world"], dtype=np.float64)
        w2c = np.linalg.inv(c2w)
        scene_camera[str(k)] = {"cam_K": np.asarray(cam["K"], dtype=np.float64).ravel().tolist(), "depth_scale": 1.0,
                                "cam_R_w2c": w2c[:3, :3].ravel().tolist(),
                                "cam_t_w2c": (1000.0 * w2c[:3, 3]).tolist()}
        gts, infos = [], []
        for g, (iid, obj_id, matrix, centre) in enumerate(instances):  # a loop over instances
            R, t = model_to_camera(matrix, centre, c2w)
            gts.append({"obj_id": int(obj_id), "cam_R_m2c": R, "cam_t_m2c": t})
            visible = ids == iid
            full = next(masks) | visible
            infos.append(gt_info(full, visible, depth))
            for sub, m in (("mask", full), ("mask_visib", visible)):
                png = io.BytesIO()
                Image.fromarray((m * 255).astype(np.uint8)).save(png, format="PNG", compress_level=1)
                files[f"{sub}/{k:06d}_{g:06d}.png"] = png.getvalue()
        scene_gt[str(k)], scene_info[str(k)] = gts, infos
    for name, data in (("scene_camera", scene_camera), ("scene_gt", scene_gt), ("scene_gt_info", scene_info)):
        files[f"{name}.json"] = (json.dumps(data, indent=1) + "\n").encode()
    return files


def write_camera(bop: Path, camera: Mapping[str, Any]) -> None:
    """``bop/camera.json`` from one view's ``K``, ``width`` and ``height``."""
    K = np.asarray(camera["K"], dtype=np.float64)
    write_text(bop / "camera.json", json.dumps({"cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1],
                                                "width": int(camera["width"]), "height": int(camera["height"]),
                                                "depth_scale": 1.0}, indent=1) + "\n")

