"""Distillation of defective meshes: does a mesh as users have it give the field of the clean one?

Per shape and defect (:mod:`regnf.benchmarks.defective_meshes`): the field is distilled from the
damaged mesh with the library's preset (:func:`regnf.training.presets.object_mesh_preset`,
the Y-up copy with ``up="y"``) and measured against the CLEAN mesh and the shape's exact SDF:

- ``surface_error_mean_rel`` / ``_p95_rel``: |SDF of the field| at 20 000 points sampled on the
  clean mesh's surface, in metres, divided by the clean mesh's bounding-box diagonal;
- ``sign_errors_rel``: the fraction of 20 000 points (uniform in the clean box grown by 10 %,
  and near the surface) more than 1 % of the diagonal from the surface where the field's sign
  differs from the exact SDF's;
- ``seconds``: the whole distillation, ``prepare_seconds`` its targets (repair, winding
  numbers, distances), and what the repair found.

Acceptance bar (issue: real-world library meshes): every defect within 0.5 % of the diagonal.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
import torch
from tqdm import tqdm

from regnf.benchmarks.defective_meshes import DEFECTS, SHAPES, DefectiveMesh, defective_mesh
from regnf.fields.field import FieldInfo
from regnf.render.evaluation import relative_surface_errors, surface_samples, world_to_field
from regnf.training.distill import DistillConfig, distill_mesh
from regnf.training.presets import object_mesh_preset

BAR_REL = 0.005
"""Acceptance bar on the mean surface error, a fraction of the diagonal."""

QUICK_CASES: tuple[tuple[str, str], ...] = (
    ("chair", "clean"), ("chair", "holes"), ("chair", "flipped"), ("chair", "components"),
)
"""``--quick``: four chair rows (a few minutes)."""

SIGN_MARGIN_REL = 0.01
"""Sign errors are counted at points farther than this fraction of the diagonal from the surface."""


def sign_error_rate(field, dm: DefectiveMesh, n: int = 20000, seed: int = 2) -> float:
    """Fraction of points away from the surface where ``field`` and the exact SDF disagree in sign.

    Half the points are uniform in the clean mesh's box grown by 10 %, half are surface samples
    offset by N(0, 2 % of the diagonal); only those more than :data:`SIGN_MARGIN_REL` of the
    diagonal from the surface count.
    """
    rng = np.random.default_rng(seed)
    lo, hi = dm.clean.bounds
    pad = 0.1 * (hi - lo)
    uniform = lo - pad + rng.random((n // 2, 3)) * (hi - lo + 2 * pad)
    near = surface_samples(dm.clean, n - n // 2, seed) + rng.normal(0.0, 0.02 * dm.diagonal, (n - n // 2, 3))
    pts = np.concatenate([uniform, near])
    truth = dm.field.sdf(torch.from_numpy(pts)).numpy()
    far = np.abs(truth) > SIGN_MARGIN_REL * dm.diagonal
    # Points outside the field's bounds are outside the object: the field is not asked there.
    local = world_to_field(field, pts[far])
    b = field.bounds.detach().cpu()
    within = ((local.cpu() >= b[0]) & (local.cpu() <= b[1])).all(dim=1).numpy()
    pred = np.ones(int(far.sum()))
    if within.any():
        pred[within] = field.sdf_chunked(local[within]).cpu().double().numpy()
    return float(((pred < 0) != (truth[far] < 0)).mean())


def measure_case(dm: DefectiveMesh, config: DistillConfig, n_surface: int = 20000) -> dict:
    """Distil ``dm.mesh`` with ``config`` (its up axis set) and measure it (see the module)."""
    cfg = dataclasses.replace(config, up=dm.up)
    t0 = time.perf_counter()
    field, log = distill_mesh(
        dm.mesh, cfg, info=FieldInfo(label="object", name=f"{dm.shape}-{dm.defect}"), progress=False,
        source=f"{dm.shape}/{dm.defect}",
    )
    seconds = time.perf_counter() - t0
    with torch.no_grad():
        err = relative_surface_errors(field, surface_samples(dm.clean, n_surface, seed=1), dm.diagonal)
        sign = sign_error_rate(field, dm)
    repair = log["repair"]
    return {
        "shape": dm.shape,
        "defect": dm.defect,
        "up": dm.up,
        "faces": len(dm.mesh.faces),
        "clean_faces": len(dm.clean.faces),
        "diagonal_m": dm.diagonal,
        "surface_error_mean_rel": float(err.mean()),
        "surface_error_p95_rel": float(np.percentile(err, 95)),
        "sign_errors_rel": sign,
        "seconds": seconds,
        "prepare_seconds": float(log["prepare_seconds"]),
        "steps": int(log["steps"]),
        "repair": repair,
        "internal_faces": int(field.info.provenance["mesh_repair"]["internal_faces"]),
        "passes": bool(err.mean() <= BAR_REL),
    }


def run_distill_benchmark(
    quick: bool = False, device: str = "cpu", on_row: Callable[[list[dict]], None] | None = None
) -> list[dict]:
    """One row per shape and defect (:data:`QUICK_CASES` with ``quick``).

    ``on_row`` is called with the rows so far after each one (to save partial results of a
    run that takes most of an hour).
    """
    cases = QUICK_CASES if quick else tuple((s, d) for s in SHAPES for d in DEFECTS)
    config = object_mesh_preset(device)
    rows: list[dict] = []
    for shape, defect in tqdm(cases, desc="bench distill", leave=False):
        rows.append(measure_case(defective_mesh(shape, defect), config))
        if on_row is not None:
            on_row(rows)
    return rows


def markdown_table(rows: list[dict]) -> str:
    """The rows as a Markdown table (errors in % of the clean mesh's bounding-box diagonal)."""
    head = (
        "| shape | defect | faces | surface mean % | surface p95 % | sign errors % | repaired | "
        "prepare s | total s | within 0.5 % |\n|---|---|---|---|---|---|---|---|---|---|\n"
    )
    body = "".join(
        f"| {r['shape']} | {r['defect']} | {r['faces']} | {100 * r['surface_error_mean_rel']:.3f} | "
        f"{100 * r['surface_error_p95_rel']:.3f} | {100 * r['sign_errors_rel']:.3f} | {repair_summary(r)} | "
        f"{r['prepare_seconds']:.1f} | {r['seconds']:.0f} | {'yes' if r['passes'] else 'NO'} |\n"
        for r in rows
    )
    return head + body


def repair_summary(row: dict) -> str:
    """What the repair did to a row's mesh, in a few words."""
    rep = row["repair"]
    parts = [
        f"{rep['merged_vertices']} merged" if rep["merged_vertices"] else "",
        f"{rep['degenerate_faces']} degenerate" if rep["degenerate_faces"] else "",
        f"{rep['duplicate_faces']} duplicates" if rep["duplicate_faces"] else "",
        f"{rep['reoriented_faces']} reoriented" if rep["reoriented_faces"] else "",
        f"{rep['open_edges']} open edges" if rep["open_edges"] else "",
        f"{rep['pieces']} pieces, {row['internal_faces']} internal" if rep["pieces"] > 1 else "",
        "turned Y-up to Z-up" if row["up"] != "z" else "",
    ]
    return ", ".join(p for p in parts if p) or "-"

