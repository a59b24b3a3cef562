"""Field benchmark: training time and accuracy of every library object and room field.

Per field: seconds to train, surface error at ground-truth surface samples, Chamfer distance
of the extracted mesh, held-out PSNR, and evaluation throughput. A field already in the
cache is reused; its ``train_seconds`` is the time measured when it was trained (recorded
in the checkpoint), and ``cached`` says so.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from regnf.core.atomic_io import write_json
from regnf.fields.field import Field
from regnf.io.checkpoint import load_field
from regnf.render.evaluation import chamfer_relative, heldout_psnr, surface_error
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.library import LIBRARY_NAMES, instance_mesh, make_library_object
from regnf.synthetic.rooms import ROOM_NAMES

QUICK_OBJECTS = ("c", "et")


def eval_throughput(field: Field, n: int = 262_144, chunk: int = 65_536) -> tuple[float, float]:
    """Points per second of ``sdf`` without grad, and of ``sdf_and_gradient`` (autograd)."""
    g = torch.Generator().manual_seed(0)
    lo, hi = field.bounds[0].cpu(), field.bounds[1].cpu()
    x = (lo + torch.rand(n, 3, generator=g) * (hi - lo)).to(field.device)
    field.sdf_chunked(x[:chunk], chunk=chunk)  # warm-up
    t = time.perf_counter()
    field.sdf_chunked(x, chunk=chunk)
    nograd = n / (time.perf_counter() - t)
    t = time.perf_counter()
    for i in range(0, n, chunk):
        field.sdf_and_gradient(x[i : i + chunk])
    grad = n / (time.perf_counter() - t)
    return nograd, grad


def measure(field: Field, path: Path, kind: str, source: str, name: str, gt_meshes, capture,
            cached: bool) -> tuple[dict, list[np.ndarray]]:
    """One benchmark row for a trained field, plus its held-out renders."""
    err = surface_error(field, gt_meshes)
    chamfer = chamfer_relative(field, gt_meshes)
    psnr, images = heldout_psnr(field, capture, indices=capture.test_indices()[:4])
    nograd, grad = eval_throughput(field)
    prov = field.info.provenance
    row = {
        "name": name,
        "kind": kind,
        "source": source,
        "train_seconds": round(float(prov.get("train_seconds", float("nan"))), 2),
        "surface_error_mean_rel": err.mean_rel,
        "surface_error_p95_rel": err.p95_rel,
        "chamfer_rel": chamfer,
        "psnr_heldout": psnr,
        "eval_points_per_second": {"nograd": round(nograd), "grad": round(grad)},
        "cached": cached,
        "checkpoint": str(path),
    }
    return row, images


def run_fields_benchmark(cache: Cache, quick: bool = False, device: str = "cpu") -> tuple[list[dict], dict]:
    """Train (or reuse) and measure every field; returns rows and held-out renders per row."""
    objects = QUICK_OBJECTS if quick else LIBRARY_NAMES
    jobs = [("object", n, s) for n in objects for s in ("rgbd", "mesh")]
    if not quick:
        jobs += [("scene", n, "rgbd") for n in ROOM_NAMES]
    rows, renders = [], {}
    fields_dir = cache.root / "fields"
    for kind, name, source in tqdm(jobs, desc="bench fields", disable=not cache.progress):
        before = set(fields_dir.glob("*.safetensors")) if fields_dir.exists() else set()
        if kind == "object":
            capture = cache.object_capture(name)
            gt = [make_library_object(name).mesh]
            path = cache.object_field(name, source, device)
        else:
            capture = cache.room_capture(name, RoomCaptureConfig(coverage="full"))
            gt = [instance_mesh(inst) for inst in capture.instances]
            path = cache.scene_field(name, "full", device)
        field = load_field(path, device=device)
        # train_seconds is what the training measured itself (kept in the checkpoint's
        # provenance), so a reused field reports the time it took when it was made.
        row, images = measure(field, path, kind, source, name, gt, capture, path in before)
        rows.append(row)
        renders[f"{name}-{source}"] = (images, [capture.rgb(i) for i in capture.test_indices()[:4]])
    return rows, renders


def contact_sheet(renders: dict, path: Path, per_row: int = 2) -> None:
    """PNG: for each field, held-out renders next to the ground truth (render | truth)."""
    import imageio.v3 as iio

    from regnf.core.atomic_io import atomic_path

    rows = []
    for (imgs, truths) in renders.values():
        tiles = [np.concatenate([im, gt], axis=1) for im, gt in list(zip(imgs, truths))[:per_row]]
        rows.append(np.concatenate(tiles, axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    sheet = (np.clip(np.concatenate(rows, axis=0), 0, 1) * 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, sheet, extension=".png")


def markdown_table(rows: list[dict]) -> str:
    """The benchmark rows as a Markdown table (errors in % of the bounding-box diagonal)."""
    head = ("| field | kind | source | train s | surface mean % | surface p95 % | Chamfer % | "
            "PSNR held-out dB | Mpts/s no-grad | Mpts/s grad |\n|---|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r['name']} | {r['kind']} | {r['source']} | {r['train_seconds']:.0f} | "
        f"{100 * r['surface_error_mean_rel']:.3f} | {100 * r['surface_error_p95_rel']:.3f} | "
        f"{100 * r['chamfer_rel']:.3f} | {r['psnr_heldout']:.1f} | "
        f"{r['eval_points_per_second']['nograd'] / 1e6:.2f} | {r['eval_points_per_second']['grad'] / 1e6:.2f} |\n"
        for r in rows
    )
    return head + body


def write_results(rows: list[dict], json_path: Path, meta: dict) -> None:
    """Write the rows (and the run's metadata) as JSON, atomically."""
    write_json(json_path, {"meta": meta, "rows": rows})
