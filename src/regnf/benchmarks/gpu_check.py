"""GPU check: the quick modes of the field, registration and render benchmarks on one device,
with the results of the CUDA-marked tests, in one JSON and one Markdown table.

``make gpu-check`` runs ``pytest -m cuda --device cuda --junitxml out/gpu_check_tests.xml``,
then ``regnf bench gpu-check --device cuda --tests out/gpu_check_tests.xml``. The tests run this
module on the CPU at the tiny size (:attr:`regnf.synthetic.cache.Cache.size`), so the path a
GPU machine takes is the one CI runs.

The JSON (documented in ``docs/benchmarks.md``)::

    {"meta": {...run_meta..., "size": "quick" | "tiny", "device_name": "NVIDIA H200" | "cpu"},
     "tests": {"file", "tests", "passed", "failed", "errors", "skipped", "failures": [names]} | null,
     "fields": {"seconds": total, "rows": [...]},        # regnf bench fields --quick
     "registration": {"seconds": total, "rows": [...]},  # regnf bench registration --quick (full
                                                         # coverage, RGB-D library, multi-view)
     "render": {"seconds": total, "rows": [...]}}        # regnf bench render --quick

Each part's rows keep the columns of its own benchmark that say how fast and how accurate.
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import torch

from regnf.core.preflight import PreflightError
from regnf.synthetic.cache import Cache

FIELD_KEYS = ("name", "source", "train_seconds", "surface_error_mean_rel", "psnr_heldout",
              "eval_points_per_second")
REGISTRATION_KEYS = ("scene", "object", "method", "seconds", "seconds_sampling", "seconds_initialisation",
                     "seconds_refinement", "rot_geodesic_rad", "trans_rel_diag", "scale_rel", "accepted")
RENDER_KEYS = ("renderer", "width", "height", "views", "seconds_per_frame", "evals_per_pixel",
               "psnr_vs_reference", "psnr_vs_neural", "bake_seconds")


def device_name(device: str) -> str:
    """The GPU's name for a CUDA device, else ``cpu``."""
    d = torch.device(device)
    return torch.cuda.get_device_name(d) if d.type == "cuda" else "cpu"


def summarise_tests(junit: Path) -> dict:
    """Counts and failed test names of a pytest ``--junitxml`` report.

    Raises
    ------
    PreflightError
        The file is missing or is not a JUnit XML report (one line naming it).
    """
    try:
        root = ET.parse(junit).getroot()
    except (OSError, ET.ParseError) as exc:
        raise PreflightError(f"--tests {junit}: not a readable JUnit XML report ({exc})") from exc
    suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
    if not suites:
        raise PreflightError(f"--tests {junit}: no <testsuite> in it (expected pytest --junitxml output)")
    failures, counts = [], {"tests": 0, "failed": 0, "errors": 0, "skipped": 0}
    for suite in suites:
        for case in suite.iter("testcase"):
            counts["tests"] += 1
            name = f"{case.get('classname', '')}::{case.get('name', '')}"
            if case.find("failure") is not None:
                counts["failed"] += 1
                failures.append(name)
            elif case.find("error") is not None:
                counts["errors"] += 1
                failures.append(name)
            elif case.find("skipped") is not None:
                counts["skipped"] += 1
    passed = counts["tests"] - counts["failed"] - counts["errors"] - counts["skipped"]
    return {"file": str(junit), **counts, "passed": passed, "failures": failures}


def _keep(rows: list[dict], keys: tuple[str, ...]) -> list[dict]:
    return [{k: r.get(k) for k in keys} for r in rows]


def run_gpu_check(cache: Cache, device: str, tests: Path | None = None,
                  on_part: Callable[[dict], None] | None = None) -> dict:
    """Every part of the check on ``device`` at ``cache.size`` (``full``: the quick modes as
    measured; ``tiny``: the same code on small captures and briefly trained fields).

    Parameters
    ----------
    cache : Cache
        Where captures and fields are made or reused.
    device : str
        Torch device of every part (``cuda``, ``cuda:1``, ``cpu``).
    tests : Path, optional
        The CUDA-marked tests' ``--junitxml`` report, summarised under ``tests``.
    on_part : callable, optional
        Called with the results so far after each part (the command rewrites its JSON, so a
        run stopped half-way keeps the parts it finished).

    Returns
    -------
    dict
        ``tests``, ``fields``, ``registration`` and ``render`` (see the module).
    """
    from regnf.benchmarks.fields import run_fields_benchmark
    from regnf.benchmarks.registration import run_registration_benchmark
    from regnf.benchmarks.render import run_render_benchmark

    summary = summarise_tests(tests) if tests is not None else None
    out: dict = {"tests": summary}
    parts = (
        ("fields", FIELD_KEYS, lambda: run_fields_benchmark(cache, quick=True, device=device)[0]),
        ("registration", REGISTRATION_KEYS,
         lambda: run_registration_benchmark(cache, quick=True, single_view=False, device=device,
                                            coverages=("full",), library_sources=("rgbd",))),
        ("render", RENDER_KEYS, lambda: run_render_benchmark(cache, device=device, quick=True)[0]["rows"]),
    )
    for name, keys, run in parts:
        t = time.perf_counter()
        rows = run()
        out[name] = {"seconds": time.perf_counter() - t, "rows": _keep(rows, keys)}
        if on_part is not None:
            on_part(out)
    return out


def _num(value: float | None, fmt: str) -> str:
    return "" if value is None else format(value, fmt)


def _pct(value: float | None) -> str:
    return "" if value is None else f"{100 * value:.2f}"


def markdown_table(result: dict) -> str:
    """The check as Markdown: the tests' counts, then one table per benchmark."""
    meta = result["meta"]
    out = [f"Device: {meta['device']} ({meta['device_name']}), size {meta['size']}, torch {meta['torch']}.", ""]
    t = result["tests"]
    if t is None:
        out += ["CUDA-marked tests: not run (no --tests report).", ""]
    else:
        out += [(f"CUDA-marked tests ({t['file']}): {t['passed']} passed, {t['failed']} failed, "
                f"{t['errors']} errors, {t['skipped']} skipped.")]
        out += [f"- failed: `{name}`" for name in t["failures"]]
        out += [""]
    sections = []
    for name, title, columns, row in _SECTIONS:
        part = result.get(name)
        if part is None:
            sections.append([f"{name.capitalize()}: not run."])
        else:
            sections.append([title.format(seconds=part["seconds"]), "", "| " + " | ".join(columns) + " |",
                             "|" + "---|" * len(columns), *(row(r) for r in part["rows"])])
    out += [line for i, sec in enumerate(sections) for line in ([""] if i else []) + sec]
    return "\n".join(out) + "\n"


_SECTIONS = (
    ("fields", "Fields (`regnf bench fields --quick`, {seconds:.0f} s in all):",
     ("field", "source", "train s", "surface mean %", "PSNR held-out dB", "Mpts/s no-grad", "Mpts/s grad"),
     lambda r: (f"| {r['name']} | {r['source']} | {r['train_seconds']:.1f} | {100 * r['surface_error_mean_rel']:.3f} | "
                f"{r['psnr_heldout']:.1f} | {r['eval_points_per_second']['nograd'] / 1e6:.2f} | "
                f"{r['eval_points_per_second']['grad'] / 1e6:.2f} |")),
    ("registration", ("Registration (`regnf bench registration --quick`, full coverage, RGB-D library, "
                      "{seconds:.0f} s in all):"),
     ("pair", "method", "s", "sampling s", "init s", "refinement s", "rotation rad", "translation %", "scale %"),
     lambda r: (f"| {r['scene']}/{r['object']} | {r['method']} | {r['seconds']:.2f} | "
                f"{_num(r['seconds_sampling'], '.2f')} | {_num(r['seconds_initialisation'], '.2f')} | "
                f"{_num(r['seconds_refinement'], '.2f')} | {_num(r['rot_geodesic_rad'], '.4f')} | "
                f"{_pct(r['trans_rel_diag'])} | {_pct(r['scale_rel'])} |")),
    ("render", "Render (`regnf bench render --quick`, composite ac-room, {seconds:.0f} s in all):",
     ("renderer", "size", "s / frame", "evals / pixel", "PSNR vs reference dB", "PSNR vs neural dB"),
     lambda r: (f"| {r['renderer']} | {r['width']}x{r['height']} | {r['seconds_per_frame']:.3f} | "
                f"{r['evals_per_pixel']:.1f} | {r['psnr_vs_reference']:.2f} | {_num(r['psnr_vs_neural'], '.2f')} |")),
)
"""Per part: its key, the title above its table, the columns, and one row's Markdown."""
