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

import html
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any, NamedTuple
from urllib.parse import quote

from regnf.core.atomic_io import atomic_path, write_text

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
        raise ValueError(f"report paths must be relative to the output folder: {rel!r}")


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


def _e(value: Any) -> str:
    """HTML-escaped text of ``value`` (quotes included); ``None`` gives an empty string."""
    return "" if value is None else html.escape(str(value), quote=True)


def _href(rel: str) -> str:
    """A relative path as an escaped URL for ``src`` / ``href`` (``/`` separators)."""
    return html.escape(quote(PurePath(rel).as_posix(), safe="/"), quote=True)


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


def _cell(text: str, classes: Sequence[str] = (), title: str | None = None) -> str:
    """One ``<td>`` with already-escaped ``text``."""
    attrs = f' class="{" ".join(classes)}"' if classes else ""
    attrs += f' title="{_e(title)}"' if title else ""
    return f"<td{attrs}>{text}</td>"


def _figure(src_rel: str, caption: str) -> str:
    """A ``<figure>`` showing (and linking to) one image, with its caption."""
    src = _href(src_rel)
    return (f'<figure><a href="{src}"><img src="{src}" alt="{_e(caption)}" loading="lazy"></a>'
            f"<figcaption>{_e(caption)}</figcaption></figure>")


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
# page


def _render_page(summary: Mapping[str, Any], sections: Sequence[Mapping[str, Any]],
                 files: Sequence[Mapping[str, Any]], registrations: Sequence[Mapping[str, Any]],
                 steps: Sequence[Mapping[str, Any]], loss_rel: str | None,
                 timings_rel: str | None) -> str:
    """The whole HTML page."""
    title = str(summary.get("title") or "regnf report")
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title>",
        f"<style>{_STYLE}</style>",
        "</head>",
        "<body>",
        _header_html(summary, title, sections),
        _timings_html(steps, _number(summary.get("total_seconds")), timings_rel),
        _registration_html(registrations, summary.get("thresholds") or {},
                           str(summary.get("registration_note") or "")),
        _loss_html(loss_rel),
        *(_section_html(i, s) for i, s in enumerate(sections)),
        _files_html(files),
        "</body>",
        "</html>",
    ]
    return "\n".join(parts) + "\n"


def _header_html(summary: Mapping[str, Any], title: str,
                 sections: Sequence[Mapping[str, Any]]) -> str:
    """Title, command, time, machine and a table of contents."""
    rows = [("command", f"<code>{_e(summary.get('command', ''))}</code>"),
            ("created", _e(summary.get("created", ""))),
            ("total time", _e(_duration(_number(summary.get("total_seconds")))))]
    machine = summary.get("machine") or {}
    rows += [(str(k), _e(v)) for k, v in machine.items()]
    items = "\n".join(f"<dt>{_e(k)}</dt><dd>{v}</dd>" for k, v in rows)
    links = [("timings", "Timings"), ("registration", "Registration"),
             ("loss-curves", "Loss curves")]
    links += [(f"section-{i}", str(s.get("title", ""))) for i, s in enumerate(sections)]
    links.append(("files", "Files"))
    nav = " ".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in links)
    return (f"<header><h1>{_e(title)}</h1>\n<dl class=\"machine\">\n{items}\n</dl>\n"
            f"<nav>{nav}</nav></header>")


def _timings_html(steps: Sequence[Mapping[str, Any]], total: float | None,
                  chart_rel: str | None) -> str:
    """The steps table and the timings chart."""
    out = ['<section id="timings"><h2>Timings</h2>']
    if not steps:
        out.append("<p>No steps recorded.</p></section>")
        return "\n".join(out)
    seconds = [_number(step.get("seconds")) for step in steps]
    step_sum = sum(s for s in seconds if s is not None)
    whole = total if total is not None and total > 0 else step_sum
    out.append('<table id="timings-table"><thead><tr><th>step</th><th>seconds</th>'
               "<th>% of total</th><th>cached</th><th>detail</th></tr></thead><tbody>")
    for step, sec in zip(steps, seconds):
        share = None if sec is None or whole <= 0 else 100.0 * sec / whole
        cached = bool(step.get("cached"))
        out.append("<tr>" + _cell(_e(step.get("name", ""))) + _cell(_fmt(sec, ".2f"), ["num"])
                   + _cell(_fmt(share, ".1f"), ["num"])
                   + _cell("yes" if cached else "no", ["ok"] if cached else [])
                   + _cell(_e(step.get("detail", ""))) + "</tr>")
    out.append("</tbody><tfoot>")
    out.append('<tr class="total">' + _cell("sum of steps") + _cell(_fmt(step_sum, ".2f"), ["num"])
               + _cell(_fmt(100.0 * step_sum / whole if whole > 0 else None, ".1f"), ["num"])
               + _cell(f"{sum(bool(s.get('cached')) for s in steps)}/{len(steps)}")
               + _cell("") + "</tr>")
    out.append("</tfoot></table>")
    if chart_rel is not None:
        out.append(f'<div class="figures">{_figure(chart_rel, "seconds per step")}</div>')
    out.append("</section>")
    return "\n".join(out)


def _metric_cell(value: float | None, metric: _Metric, compared: float | None,
                 thresholds: Mapping[str, Any]) -> str:
    """One error cell, classed ``bad`` / ``ok`` when its quantity has a target."""
    shown = None if value is None else value * metric.factor
    limit = _number(thresholds.get(metric.threshold_key)) if metric.threshold_key else None
    classes = ["num"]
    title = None
    if limit is not None and compared is not None:
        # A NaN error fails the comparison, so it is marked bad as well.
        within = compared <= limit
        classes.append("ok" if within else "bad")
        title = f"target ≤ {limit:g} ({metric.threshold_key})"
    return _cell(_fmt(shown, metric.spec), classes, title)


def _registration_row(values: Mapping[str, float | None], thresholds: Mapping[str, Any]) -> str:
    """The error and time cells of one row (an instance or the medians)."""
    cells = [_metric_cell(values[m.key], m, values.get(m.threshold_key or ""), thresholds)
             for m in _METRICS]
    cells.append(_cell(_fmt(values["seconds"], ".1f"), ["num"]))
    return "".join(cells)


def _registration_html(registrations: Sequence[Mapping[str, Any]],
                       thresholds: Mapping[str, Any], note: str = "") -> str:
    """The table of registration errors against ground truth, with a median row, then ``note``."""
    out = ['<section id="registration"><h2>Registration against ground truth</h2>']
    if not registrations:
        out.append("<p>No registrations.</p></section>")
        return "\n".join(out)
    keys = sorted({m.key for m in _METRICS} | {"confidence", "seconds"})
    table = [{k: _number(reg.get(k)) for k in keys} for reg in registrations]
    headers = ["instance", "object", "confidence", "accepted", *(m.header for m in _METRICS),
               "seconds"]
    out.append('<table id="registration-table"><thead><tr>'
               + "".join(f"<th>{_e(h)}</th>" for h in headers) + "</tr></thead><tbody>")
    for reg, values in zip(registrations, table):
        obj = _e(reg.get("object", ""))
        if reg.get("label"):
            obj += f" ({_e(reg['label'])})"
        accepted = bool(reg.get("accepted"))
        out.append("<tr>" + _cell(_e(reg.get("instance", ""))) + _cell(obj)
                   + _cell(_fmt(values["confidence"], ".3f"), ["num"])
                   + _cell("yes" if accepted else "no", [] if accepted else ["warn"])
                   + _registration_row(values, thresholds) + "</tr>")
    medians = {k: _median(row[k] for row in table) for k in keys}
    n_accepted = sum(bool(reg.get("accepted")) for reg in registrations)
    out.append('</tbody><tfoot><tr class="median">' + _cell("median") + _cell("")
               + _cell(_fmt(medians["confidence"], ".3f"), ["num"])
               + _cell(f"{n_accepted}/{len(registrations)}")
               + _registration_row(medians, thresholds) + "</tr></tfoot></table>")
    out.append(_targets_note(thresholds))
    if note:
        out.append(f"<p>{_e(note)}</p>")
    out.append("</section>")
    return "\n".join(out)


def _targets_note(thresholds: Mapping[str, Any]) -> str:
    """A sentence stating the acceptance targets the marks refer to."""
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
    if not targets:
        return '<p class="note">No acceptance targets given.</p>'
    return ('<p class="note">Targets: ' + _e(", ".join(targets))
            + ". Cells outside their target are marked in red with a cross.</p>")


def _loss_html(chart_rel: str | None) -> str:
    """The loss-curve chart, or a note that there is no history."""
    out = ['<section id="loss-curves"><h2>Loss curves</h2>']
    if chart_rel is None:
        out.append("<p>No refinement history.</p>")
    else:
        caption = "registration loss (and scale s) against iteration, one line per instance"
        out.append(f'<div class="figures">{_figure(chart_rel, caption)}</div>')
    out.append("</section>")
    return "\n".join(out)


def _section_html(index: int, section: Mapping[str, Any]) -> str:
    """One image section: its title, paragraph and figures."""
    out = [f'<section id="section-{index}"><h2>{_e(section.get("title", ""))}</h2>']
    if section.get("text"):
        out.append(f"<p>{_e(section['text'])}</p>")
    figures = [_figure(str(image["path"]), str(image.get("caption", "")))
               for image in section.get("images") or []]
    if figures:
        out.append('<div class="figures">\n' + "\n".join(figures) + "\n</div>")
    out.append("</section>")
    return "\n".join(out)


def _files_html(files: Sequence[Mapping[str, Any]]) -> str:
    """Links to the run's other outputs."""
    out = ['<section id="files"><h2>Files</h2>']
    if not files:
        out.append("<p>No files listed.</p>")
    else:
        out.append("<ul>")
        for entry in files:
            rel = str(entry["path"])
            what = f" — {_e(entry['what'])}" if entry.get("what") else ""
            out.append(f'<li><a href="{_href(rel)}"><code>{_e(rel)}</code></a>{what}</li>')
        out.append("</ul>")
    out.append("</section>")
    return "\n".join(out)
