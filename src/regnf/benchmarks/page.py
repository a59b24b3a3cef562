"""The one results page, ``docs/benchmarks.md``, made from the benchmarks' JSON by ``regnf bench page``.

Each benchmark writes a JSON file (``--json``) with a ``meta`` block (command, date, device,
torch, threads, CPU) and its rows. The page reads one file per benchmark from a results folder
(``docs/results/<name>.json``), says once at the top which machine and which dates they come
from, and shows each benchmark's compact tables; a benchmark with no file gets the command that
records one. The page is never edited by hand: rerun a benchmark with ``--json
docs/results/<name>.json``, then ``regnf bench page``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from regnf.core.atomic_io import write_text
from regnf.core.errors import RegnfError


class Section(NamedTuple):
    """One benchmark on the page."""

    name: str
    """File stem in the results folder, and ``regnf bench NAME``."""
    title: str
    """The section's heading."""
    record: str
    """The options that record the result the page shows (after ``regnf bench NAME``)."""
    tables: Callable[[dict], str]
    """The section's Markdown from the JSON."""
    images: str = ""
    """Glob, beside the JSON, of the PNGs the section links (what the benchmark drew), or none."""


def _fields(data: dict) -> str:
    from regnf.benchmarks.fields import markdown_table

    return markdown_table(data["rows"])


def _registration(data: dict) -> str:
    from regnf.benchmarks.registration_report import (
        coverage_table,
        is_reference,
        medians,
        wrong_pair_table,
    )

    rows = data["rows"]
    text = f"Per coverage and library, method `regnf`:\n\n{coverage_table(rows)}"
    if any(is_reference(r) for r in rows):
        text += f"\nMedians of every method over the full-coverage pairs, RGB-D library:\n\n{medians(rows)}"
    if any(r.get("wrong_pair") for r in rows):
        text += f"\nWrong-object pairs:\n\n{wrong_pair_table(rows)}"
    return text


def _discover(data: dict) -> str:
    from regnf.benchmarks.discover import markdown_table

    return markdown_table(data["rows"])


def _render(data: dict) -> str:
    from regnf.benchmarks.render_report import markdown_tables

    return markdown_tables(data)


def _distill(data: dict) -> str:
    from regnf.benchmarks.distill import markdown_table

    return markdown_table(data["rows"])


def _encodings(data: dict) -> str:
    from regnf.benchmarks.encodings import markdown_table

    return markdown_table(data["rows"])


def _sensor(data: dict) -> str:
    from regnf.benchmarks.sensor_report import summary_table

    return summary_table(data["summary"])


def _capture_scale(data: dict) -> str:
    from regnf.benchmarks.capture_scale import markdown_table

    return markdown_table(data)


def _viewer(data: dict) -> str:
    keys = [k for k in ("instances_listed_s", "first_render_s", "refined_render_s") if k in data]
    text = "| " + " | ".join(keys) + " |\n|" + "---|" * len(keys) + "\n| " + " | ".join(
        f"{data[k]:.1f}" for k in keys) + " |\n"
    fixes = data.get("corrections") or []
    if fixes:
        ok = sum(bool(c["accepted"]) and bool(c["within_bars"]) for c in fixes)
        text += (f"\nPose corrections from a dragged pose: {ok} of {len(fixes)} accepted and within the bars "
                 f"(worst: {max(c['rot_geodesic_rad'] for c in fixes):.4f} rad, "
                 f"{100 * max(c['trans_rel_diag'] for c in fixes):.2f} % of the diagonal, "
                 f"{100 * max(c['scale_rel'] for c in fixes):.2f} % in scale).\n")
    return text


def _gpu_check(data: dict) -> str:
    from regnf.benchmarks.gpu_check import markdown_table

    return markdown_table(data)


SECTIONS = (
    Section("fields", "Fields: training time and surface error", "", _fields, "fields.png"),
    Section("registration", "Registration from true boxes", "--coverage both --library mesh", _registration),
    Section("discover", "Discovery without boxes", "", _discover, "discover_png/*.png"),
    Section("render", "Rendering and object completion", "", _render, "render_*.png"),
    Section("distill", "Distillation of defective meshes", "", _distill),
    Section("encodings", "Feature encodings", "", _encodings),
    Section("sensor", "Sensor noise and pose error", "", _sensor),
    Section("capture-scale", "Real captures: hundreds of frames", "--frames 100 300 600 --pixel-stride 2",
            _capture_scale),
    Section("viewer", "The viewer", "out/demo/stage/ac-room.usda", _viewer),
    Section("gpu-check", "GPU check", "--device cuda", _gpu_check),
)
"""Every benchmark, in the page's order."""


def _read(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RegnfError(f"{path}: not a readable benchmark result ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("meta"), dict):
        raise RegnfError(f"{path}: not a benchmark result (no 'meta' block)")
    return data


def _machine(meta: dict) -> str:
    return (f"{meta.get('cpu', '?')}, {meta.get('threads', '?')} torch threads, torch {meta.get('torch', '?')}, "
            f"device {meta.get('device', '?')}")


def _image_links(folder: Path, section: Section, page_dir: Path) -> list[str]:
    """A line linking the section's pictures, relative to the page's folder (none: no line)."""
    pngs = sorted(folder.glob(section.images)) if section.images else []
    if not pngs:
        return []
    links = [f"[{p.stem}]({Path(os.path.relpath(p, page_dir)).as_posix()})" for p in pngs]
    return ["Pictures: " + ", ".join(links) + ".", ""]


def results_page(results: str | os.PathLike, page_dir: str | os.PathLike | None = None) -> str:
    """The page's Markdown from the JSON files in ``results`` (``<section name>.json``); its links
    to pictures are relative to ``page_dir`` (default: the folder above ``results``)."""
    folder = Path(results)
    page_dir = Path(page_dir) if page_dir is not None else folder.absolute().parent
    if not folder.is_dir():
        raise RegnfError(f"{folder}: no such folder of benchmark results")
    found = {s.name: _read(folder / f"{s.name}.json") for s in SECTIONS if (folder / f"{s.name}.json").is_file()}
    metas = [d["meta"] for d in found.values()]
    machines = sorted({_machine(m) for m in metas})
    dates = sorted(str(m.get("date", "?"))[:10] for m in metas)
    head = ["# Benchmarks", "",
            f"Generated by `regnf bench page` from the JSON results in `{folder.as_posix()}/`; not edited by hand.",
            "To refresh a section, run the command it names, then `regnf bench page`.", ""]
    if metas:
        where = machines[0] if len(machines) == 1 else "; ".join(machines)
        when = dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}"
        head += [f"Machine: {where}. Runs: {when}.", ""]
    body = []
    for s in SECTIONS:
        body += [f"## {s.title}", ""]
        if s.name not in found:
            command = " ".join(filter(None, ("regnf bench", s.name, s.record,
                                             f"--json {folder.as_posix()}/{s.name}.json")))
            body += [f"No result recorded yet: `{command}`.", ""]
            continue
        meta = found[s.name]["meta"]
        machine = "" if len(machines) == 1 else f" on {_machine(meta)}"
        body += [f"`{meta.get('command', '?')}`, {str(meta.get('date', '?'))[:10]}{machine}.", "",
                 s.tables(found[s.name]).rstrip("\n"), "", *_image_links(folder, s, page_dir)]
    return "\n".join(head + body).rstrip("\n") + "\n"


def write_results_page(results: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write :func:`results_page` to ``out`` (atomically); returns the path."""
    write_text(out, results_page(results, Path(out).absolute().parent))
    return Path(out)
