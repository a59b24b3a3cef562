"""A self-contained HTML report of an end-to-end demo run.

:func:`write_report` turns the run's summary (a JSON-able mapping) into ``report.html`` in
the run's output folder ``out``. The page has, in order:

* a header: title, command line, creation time, the machine (CPU count, device, library
  versions, platform) and the total time;
* **Timings**: a table of the steps (seconds, share of the total, whether the result came
  from the cache, a short detail) and a horizontal bar chart of the same;
* **Registration against ground truth**: one row per instance with its confidence, whether
  it was accepted, the rotation error (degrees and radians), the translation error
  (millimetres and percent of the bounding-box diagonal), the scale error (percent) and the
  time taken, then a median row. A cell outside its acceptance target is given the class
  ``bad`` (shown in red with a cross), one within it the class ``ok``;
* **Loss curves**: the refinement loss (and the scale ``s`` where recorded) against the
  iteration, one line per instance;
* each image section of the summary, with its paragraph and its figures;
* **Files**: links to the run's other outputs (stage, USDZ, ...).

Layout written under ``out``::

    report.html                 the page (UTF-8, inline style, no scripts, no external resources)
    report/loss_curves.png      loss and scale against iteration (absent without any history)
    report/timings.png          seconds per step (absent without any step)

Every link and image source is a path relative to ``out``, so the folder can be moved or
zipped and still opens. Every image and file the summary names must exist under ``out``;
otherwise nothing is written. Each file is written atomically, the page last, so the page
never points at a chart that is not there.

Summary keys (all optional; paths relative to ``out``)::

    title, command, created (ISO time), machine (mapping), total_seconds,
    steps:         [{name, seconds, cached, detail}]
    registrations: [{instance, object, label, accepted, confidence, rot_geodesic_rad,
                     trans_m, trans_rel_diag, scale_rel, seconds,
                     history: [{iteration, loss, s, ...}]}]
    thresholds:    {rot_geodesic_rad, trans_rel_diag, scale_rel}
    registration_note: a paragraph under the registration table
    sections:      [{title, text, images: [{path, caption}]}]
    files:         [{path, what}]
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any, NamedTuple
from urllib.parse import quote

from regnf.core.atomic_io import atomic_path, write_text
from regnf.core.errors import RegnfError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

REPORT_NAME = "report.html"
"""The page's file name in the output folder."""
ASSET_DIR = "report"
"""Folder (relative to the output folder) of the charts the page shows."""
LOSS_CURVES_NAME = "loss_curves.png"
"""File name of the loss-curve chart in :data:`ASSET_DIR`."""
TIMINGS_NAME = "timings.png"
"""File name of the timings chart in :data:`ASSET_DIR`."""
DPI = 100
"""Resolution of the charts."""
TEMPLATE_NAME = "report.html.j2"
"""The page's template in ``regnf/templates`` (jinja2, every value escaped)."""

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 80em; padding: 0 1em;
       color: #222; line-height: 1.4; }
h1 { margin-bottom: 0.2em; }
h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 2em; }
code { background: #f3f3f3; padding: 0 0.2em; }
nav a { margin-right: 1em; }
table { border-collapse: collapse; margin: 0.8em 0; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: left; }
th { background: #f3f3f3; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.bad { color: #b00020; background: #fde7ea; font-weight: bold; }
td.bad::after { content: " \\2717"; }
td.ok { color: #1b5e20; }
td.warn { color: #b26a00; }
tr.median td, tr.total td { border-top: 2px solid #999; font-style: italic; }
dl.machine { display: grid; grid-template-columns: max-content auto; gap: 0.1em 1em; }
dl.machine dt { font-weight: bold; }
dl.machine dd { margin: 0; }
.figures { display: flex; flex-wrap: wrap; gap: 1em; }
figure { margin: 0; max-width: 100%; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
p.note { color: #555; font-size: 0.9em; }
"""


class _Metric(NamedTuple):
    """One numeric column of the registration table."""

    header: str
    """Column heading."""
    key: str
    """Registration key the value is read from."""
    factor: float
    """Multiplier from the stored unit to the shown one."""
    spec: str
    """Format specification of the shown value."""
    threshold_key: str | None
    """Key in ``thresholds`` the stored value is compared with, if any."""


_METRICS = (
    _Metric("rotation (°)", "rot_geodesic_rad", 180.0 / math.pi, ".3f", "rot_geodesic_rad"),
    _Metric("rotation (rad)", "rot_geodesic_rad", 1.0, ".5f", "rot_geodesic_rad"),
    _Metric("translation (mm)", "trans_m", 1000.0, ".2f", "trans_rel_diag"),
    _Metric("translation (% diag)", "trans_rel_diag", 100.0, ".3f", "trans_rel_diag"),
    _Metric("scale (%)", "scale_rel", 100.0, ".3f", "scale_rel"),
)
"""The error columns. Both units of one quantity are marked by that quantity's target;
the millimetre column by the relative translation of the same row."""


def write_report(out: str | os.PathLike, summary: Mapping[str, Any]) -> Path:
    """Write ``out/report.html`` (and its charts under ``out/report/``) from ``summary``.

    Parameters
    ----------
    out : str or os.PathLike
        The run's output folder; every path in ``summary`` is relative to it.
    summary : Mapping[str, Any]
        The run's summary (see the module docstring for its keys).

    Returns
    -------
    Path
        The path of the written ``report.html``.

    Raises
    ------
    FileNotFoundError
        If an image of ``sections`` or an entry of ``files`` does not exist under ``out``;
        the message names every missing path and nothing is written.
    ValueError
        If such a path is absolute or climbs out of ``out`` with ``..`` (the page would then
        break when the folder is moved).
    """
    root = Path(out)
    sections = list(summary.get("sections") or [])
    files = list(summary.get("files") or [])
    _check_present(root, sections, files)

    registrations = list(summary.get("registrations") or [])
    steps = list(summary.get("steps") or [])
    loss_rel = _write_chart(root, LOSS_CURVES_NAME, _loss_figure(registrations))
    timings_rel = _write_chart(root, TIMINGS_NAME, _timings_figure(steps))

    page = _render_page(summary, sections, files, registrations, steps, loss_rel, timings_rel)
    path = root / REPORT_NAME
    write_text(path, page)
    return path


# ---------------------------------------------------------------------------------------------
# checks


def _check_relative(rel: str) -> None:
    """Raise ``ValueError`` unless ``rel`` is a relative path that stays inside its folder."""
    p = PurePath(rel)
    if not rel or p.is_absolute() or p.anchor or ".." in p.parts:
        raise RegnfError(f"report paths must be relative to the output folder: {rel!r}")


def _check_present(root: Path, sections: Sequence[Mapping[str, Any]],
                   files: Sequence[Mapping[str, Any]]) -> None:
    """Raise ``FileNotFoundError`` naming every section image or listed file missing under root."""
    missing: list[str] = []
    for section in sections:
        for image in section.get("images") or []:
            rel = str(image["path"])
            _check_relative(rel)
            if not (root / rel).is_file() and rel not in missing:
                missing.append(rel)
    for entry in files:
        rel = str(entry["path"])
        _check_relative(rel)
        if not (root / rel).exists() and rel not in missing:
            missing.append(rel)
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} file(s) named by the report summary missing under {root}: "
            + ", ".join(missing))


# ---------------------------------------------------------------------------------------------
# small formatting helpers


def _number(value: Any) -> float | None:
    """``value`` as a float, or ``None`` when it is not a number (booleans are not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value)


def _fmt(value: float | None, spec: str) -> str:
    """Format a number, with a dash for a missing one."""
    return "–" if value is None else format(value, spec)


def _duration(seconds: float | None) -> str:
    """``612.3 s (10 min 12 s)``; plain seconds below a minute, a dash when unknown."""
    if seconds is None:
        return "–"
    text = f"{seconds:.1f} s"
    if seconds >= 60 and math.isfinite(seconds):
        minutes, rest = divmod(round(seconds), 60)
        hours, minutes = divmod(minutes, 60)
        parts = ([f"{hours} h"] if hours else []) + [f"{minutes} min", f"{rest} s"]
        text += f" ({' '.join(parts)})"
    return text


def _median(values: Iterable[float | None]) -> float | None:
    """Median of the finite values, ``None`` if there are none."""
    finite = sorted(v for v in values if v is not None and math.isfinite(v))
    if not finite:
        return None
    mid = len(finite) // 2
    return finite[mid] if len(finite) % 2 else 0.5 * (finite[mid - 1] + finite[mid])


# ---------------------------------------------------------------------------------------------
# charts


def _new_figure(width: float, height: float) -> Figure:
    """A matplotlib figure drawn by the Agg canvas, independent of pyplot's global state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _write_chart(root: Path, name: str, fig: Figure | None) -> str | None:
    """Save ``fig`` atomically as ``root/report/name``; return its relative path.

    Without a figure, a chart left by an earlier run is removed so the folder matches the page.
    """
    rel = f"{ASSET_DIR}/{name}"
    path = root / rel
    if fig is None:
        path.unlink(missing_ok=True)
        return None
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return rel


def _series(history: Sequence[Mapping[str, Any]], key: str) -> tuple[list[float], list[float]]:
    """Iterations and values of ``key`` over a history (entries without the key skipped)."""
    xs: list[float] = []
    ys: list[float] = []
    for i, entry in enumerate(history):
        y = _number(entry.get(key))
        if y is None:
            continue
        x = _number(entry.get("iteration"))
        xs.append(float(i) if x is None else x)
        ys.append(y)
    return xs, ys


def _instance_label(reg: Mapping[str, Any]) -> str:
    """``c_1 (c)``: the instance and the library object registered to it."""
    name = str(reg.get("instance", "?"))
    obj = reg.get("object")
    return name if obj is None else f"{name} ({obj})"


def _loss_figure(registrations: Sequence[Mapping[str, Any]]) -> Figure | None:
    """Loss (and scale ``s``) against iteration, one line per instance; ``None`` without data."""
    curves = []
    for reg in registrations:
        history = list(reg.get("history") or [])
        loss = _series(history, "loss")
        if loss[0]:
            curves.append((_instance_label(reg), loss, _series(history, "s")))
    if not curves:
        return None
    with_scale = any(scale[0] for _, _, scale in curves)
    fig = _new_figure(11.0 if with_scale else 7.0, 4.5)
    axes = fig.subplots(1, 2 if with_scale else 1, squeeze=False)[0]
    colours = _colours(len(curves))
    for colour, (label, (xs, ys), (sx, sy)) in zip(colours, curves):
        axes[0].plot(xs, ys, color=colour, label=label, linewidth=1.2)
        if with_scale and sx:
            axes[1].plot(sx, sy, color=colour, label=label, linewidth=1.2)
    losses = [y for _, (_, ys), _ in curves for y in ys if math.isfinite(y)]
    if losses and min(losses) > 0:
        axes[0].set_yscale("log")
    axes[0].set(xlabel="iteration", ylabel="loss", title="registration loss")
    axes[0].grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize="small", ncol=1 + len(curves) // 12)
    if with_scale:
        axes[1].set(xlabel="iteration", ylabel="scale s", title="scale")
        axes[1].grid(True, alpha=0.3)
    return fig


def _colours(n: int) -> list[Any]:
    """``n`` distinguishable line colours (the default cycle, ``tab20`` beyond ten)."""
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _timings_figure(steps: Sequence[Mapping[str, Any]]) -> Figure | None:
    """Horizontal bars of the seconds per step, top to bottom in order; ``None`` without steps."""
    if not steps:
        return None
    from matplotlib.patches import Patch

    names = [str(step.get("name", f"step {i}")) for i, step in enumerate(steps)]
    seconds = [_number(step.get("seconds")) or 0.0 for step in steps]
    cached = [bool(step.get("cached")) for step in steps]
    fig = _new_figure(8.0, 1.2 + 0.32 * len(steps))
    ax = fig.add_subplot()
    colours = ["#9e9e9e" if c else "#1f77b4" for c in cached]
    bars = ax.barh(range(len(steps)), seconds, color=colours)
    ax.bar_label(bars, labels=[f"{s:.1f} s" for s in seconds], padding=3, fontsize="small")
    ax.set_yticks(range(len(steps)), labels=names)
    ax.invert_yaxis()
    ax.set_xlabel("seconds")
    ax.set_title("time per step")
    ax.margins(x=0.15)
    ax.grid(True, axis="x", alpha=0.3)
    if any(cached):
        ax.legend(handles=[Patch(color="#1f77b4", label="computed"),
                           Patch(color="#9e9e9e", label="cached")], fontsize="small")
    return fig


# ---------------------------------------------------------------------------------------------
# page: the numbers are formatted here, the markup is templates/report.html.j2 (autoescaped)


class _Cell(NamedTuple):
    """One table cell: its text (escaped by the template), CSS classes and tooltip."""

    text: str
    classes: tuple[str, ...] = ()
    title: str | None = None


class _Figure(NamedTuple):
    """One image of the page: its URL-quoted relative path and its caption."""

    src: str
    caption: str


def _figure(src_rel: str, caption: str) -> _Figure:
    """A figure showing (and linking to) one image."""
    return _Figure(quote(PurePath(src_rel).as_posix(), safe="/"), caption)


def _template() -> Any:
    """The page template, escaping every value it is given (``Markup`` excepted)."""
    import jinja2

    env = jinja2.Environment(loader=jinja2.PackageLoader("regnf", "templates"), autoescape=True,
                             undefined=jinja2.StrictUndefined, keep_trailing_newline=True)
    return env.get_template(TEMPLATE_NAME)


def _render_page(summary: Mapping[str, Any], sections: Sequence[Mapping[str, Any]],
                 files: Sequence[Mapping[str, Any]], registrations: Sequence[Mapping[str, Any]],
                 steps: Sequence[Mapping[str, Any]], loss_rel: str | None,
                 timings_rel: str | None) -> str:
    """The whole HTML page."""
    from markupsafe import Markup

    title = str(summary.get("title") or "regnf report")
    machine = summary.get("machine") or {}
    header = [("command", str(summary.get("command", "")), True),
              ("created", str(summary.get("created", "")), False),
              ("total time", _duration(_number(summary.get("total_seconds"))), False)]
    header += [(str(k), str(v), False) for k, v in machine.items()]
    nav = [("timings", "Timings"), ("registration", "Registration"), ("loss-curves", "Loss curves")]
    nav += [(f"section-{i}", str(s.get("title", ""))) for i, s in enumerate(sections)]
    nav.append(("files", "Files"))
    return _template().render(
        title=title, style=Markup(_STYLE), header=header, nav=nav,
        timings=_timings(steps, _number(summary.get("total_seconds")), timings_rel),
        registration=_registration(registrations, summary.get("thresholds") or {}),
        registration_note=str(summary.get("registration_note") or ""),
        loss_chart=None if loss_rel is None else _figure(
            loss_rel, "registration loss (and scale s) against iteration, one line per instance"),
        sections=[{"title": str(s.get("title", "")), "text": str(s.get("text") or ""),
                   "figures": [_figure(str(im["path"]), str(im.get("caption", "")))
                               for im in s.get("images") or []]} for s in sections],
        files=[{"href": quote(PurePath(str(f["path"])).as_posix(), safe="/"), "path": str(f["path"]),
                "what": str(f.get("what") or "")} for f in files],
    )


def _timings(steps: Sequence[Mapping[str, Any]], total: float | None,
             chart_rel: str | None) -> dict[str, Any] | None:
    """Rows of the steps table, its total row and the chart; None without steps."""
    if not steps:
        return None
    seconds = [_number(step.get("seconds")) for step in steps]
    step_sum = sum(s for s in seconds if s is not None)
    whole = total if total is not None and total > 0 else step_sum
    rows = []
    for step, sec in zip(steps, seconds):
        share = None if sec is None or whole <= 0 else 100.0 * sec / whole
        cached = bool(step.get("cached"))
        rows.append([_Cell(str(step.get("name", ""))), _Cell(_fmt(sec, ".2f"), ("num",)),
                     _Cell(_fmt(share, ".1f"), ("num",)),
                     _Cell("yes" if cached else "no", ("ok",) if cached else ()),
                     _Cell(str(step.get("detail", "")))])
    total_row = [_Cell("sum of steps"), _Cell(_fmt(step_sum, ".2f"), ("num",)),
                 _Cell(_fmt(100.0 * step_sum / whole if whole > 0 else None, ".1f"), ("num",)),
                 _Cell(f"{sum(bool(s.get('cached')) for s in steps)}/{len(steps)}"), _Cell("")]
    chart = None if chart_rel is None else _figure(chart_rel, "seconds per step")
    return {"rows": rows, "total": total_row, "chart": chart}


def _metric_cell(value: float | None, metric: _Metric, compared: float | None,
                 thresholds: Mapping[str, Any]) -> _Cell:
    """One error cell, classed ``bad`` / ``ok`` when its quantity has a target."""
    shown = None if value is None else value * metric.factor
    limit = _number(thresholds.get(metric.threshold_key)) if metric.threshold_key else None
    classes: tuple[str, ...] = ("num",)
    title = None
    if limit is not None and compared is not None:
        # A NaN error fails the comparison, so it is marked bad as well.
        within = compared <= limit
        classes += ("ok" if within else "bad",)
        title = f"target ≤ {limit:g} ({metric.threshold_key})"
    return _Cell(_fmt(shown, metric.spec), classes, title)


def _registration_row(values: Mapping[str, float | None], thresholds: Mapping[str, Any]) -> list[_Cell]:
    """The error and time cells of one row (an instance or the medians)."""
    cells = [_metric_cell(values[m.key], m, values.get(m.threshold_key or ""), thresholds)
             for m in _METRICS]
    return [*cells, _Cell(_fmt(values["seconds"], ".1f"), ("num",))]


def _registration(registrations: Sequence[Mapping[str, Any]],
                  thresholds: Mapping[str, Any]) -> dict[str, Any] | None:
    """The table of registration errors against ground truth with its median row; None if empty."""
    if not registrations:
        return None
    keys = sorted({m.key for m in _METRICS} | {"confidence", "seconds"})
    table = [{k: _number(reg.get(k)) for k in keys} for reg in registrations]
    headers = ["instance", "object", "confidence", "accepted", *(m.header for m in _METRICS), "seconds"]
    rows = []
    for reg, values in zip(registrations, table):
        obj = str(reg.get("object", ""))
        if reg.get("label"):
            obj += f" ({reg['label']})"
        accepted = bool(reg.get("accepted"))
        rows.append([_Cell(str(reg.get("instance", ""))), _Cell(obj),
                     _Cell(_fmt(values["confidence"], ".3f"), ("num",)),
                     _Cell("yes" if accepted else "no", () if accepted else ("warn",)),
                     *_registration_row(values, thresholds)])
    medians = {k: _median(row[k] for row in table) for k in keys}
    n_accepted = sum(bool(reg.get("accepted")) for reg in registrations)
    median = [_Cell("median"), _Cell(""), _Cell(_fmt(medians["confidence"], ".3f"), ("num",)),
              _Cell(f"{n_accepted}/{len(registrations)}"), *_registration_row(medians, thresholds)]
    return {"headers": headers, "rows": rows, "median": median, "targets": _targets(thresholds)}


def _targets(thresholds: Mapping[str, Any]) -> str | None:
    """A sentence stating the acceptance targets the marks refer to (None without targets)."""
    rot = _number(thresholds.get("rot_geodesic_rad"))
    trans = _number(thresholds.get("trans_rel_diag"))
    scale = _number(thresholds.get("scale_rel"))
    targets = []
    if rot is not None:
        targets.append(f"rotation ≤ {math.degrees(rot):.3g}° ({rot:g} rad)")
    if trans is not None:
        targets.append(f"translation ≤ {100 * trans:.3g} % of the bounding-box diagonal")
    if scale is not None:
        targets.append(f"scale ≤ {100 * scale:.3g} %")
    return ", ".join(targets) or None
