"""Tables and pictures of the render benchmark."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from regnf.compositor.contact_sheets import contact_sheet
from regnf.core.atomic_io import atomic_path


def markdown_tables(result: dict) -> str:
    """The speed rows, and the completion and replacement summaries where the run made them, as Markdown."""
    out = [("| scene | renderer | size | evals / pixel | s / frame | PSNR vs reference (dB) | "
            "PSNR vs neural (dB) | bake s |"),
           "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        vs = f"{r['psnr_vs_neural']:.2f} (min {r['psnr_vs_neural_min']:.2f})" if "psnr_vs_neural" in r else ""
        bake = f"{r['bake_seconds']:.0f}" if "bake_seconds" in r else ""
        out.append(f"| {r['scene']} | {r['renderer']} | {r['width']}x{r['height']} | "
                   f"{r['evals_per_pixel']:.1f} | {r['seconds_per_frame']:.2f} | {r['psnr_vs_reference']:.2f} | "
                   f"{vs} | {bake} |")
    c = result.get("completion")
    if c:
        out += completion_table(c)
    r = result.get("replacement")
    if r:
        out += replacement_table(r)
    return "\n".join(out) + "\n"


def completion_table(c: dict) -> list[str]:
    """Lines of the completion summary's Markdown table."""
    out = ["", (f"Object completion, {c['scene']}, {c['views_per_object']} unseen views per object "
                "(object pixels only):"), "",
           "| object | PSNR before (dB) | PSNR after (dB) | depth MAE before (m) | depth MAE after (m) |",
           "|---|---|---|---|---|"]
    for o in [*c["objects"], {"object": "**mean**", **c}]:
        out.append(f"| {o['object']} | {o['psnr_before']:.2f} | {o['psnr_after']:.2f} | "
                   f"{o['depth_mae_before']:.4f} | {o['depth_mae_after']:.4f} |")
    return out


def replacement_table(r: dict) -> list[str]:
    """Lines of the replacement records' Markdown table."""
    out = ["", (f"Random instance replacement, {r['scene']}, every instance swapped for another object "
                f"of its class, {r['views']} views:"), "",
           ("| seed | selections | floor gap (% of height) | heading error (rad) | penetration (mm) "
            "| remnant pixels / removed-object pixels |"), "|---|---|---|---|---|---|"]
    for x in r["seeds"]:
        sel = ", ".join(f"{k}->{v}" for k, v in x["selections"].items())
        out.append(f"| {x['seed']} | {sel} | {100 * x['floor_gap_rel_height_max']:.2f} | "
                   f"{x['heading_error_rad_max']:.4f} | {1000 * x['penetration_m_max']:.1f} | "
                   f"{x['remnant_pixels']} / {x['removed_object_pixels']} |")
    return out


def write_images(images: dict[str, list[np.ndarray]], folder: Path, stem: str) -> list[Path]:
    """One contact sheet per image group: ``<stem>_speed.png`` (reference, then one image per
    speed row: sphere tracer, baked, matched sphere tracer, volume renderer) and ``<stem>_completion.png`` (per object: before,
    after, reference)."""
    paths = []
    for name, imgs in images.items():
        if not imgs:
            continue
        columns = len(imgs) if name == "speed" else 1
        sheet = contact_sheet(imgs, columns=columns, tile_width=imgs[0].shape[1])
        path = Path(folder) / f"{stem}_{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            Image.fromarray(sheet).save(tmp, format="PNG")
        paths.append(path)
    return paths
