"""The sensor benchmark's verdicts, computed from its rows, and its Markdown tables.

Per level and coverage, :func:`summarise` counts the rows and runs the checks of issue
"Real captures" that apply at that level (:data:`LEVEL_CHECKS`):

- ``bars`` (``ideal``, ``sensor``): every true-box pair accepted and within the plain bars
  (:data:`regnf.registration.metrics.BARS`);
- ``widened`` (``slam``): every true-box pair accepted and within the bars widened by the
  error of the cameras that see the object (:func:`regnf.benchmarks.sensor.widened_bars`);
- ``discovery`` (``sensor``): of the true instances of the rooms run, all but at most one
  identified within the plain bars (10 of 11 with the three rooms), and no false instance;
- at every level: no accepted pair outside the widened bars, and no wrong object accepted.

A wrong pair is a wrong object accepted when it is accepted and either its object is of
another class than the box's, or it is a chair scoring at least the right chair's confidence
in that box where the scene observed what tells the two apart (the registration benchmark's
:func:`regnf.benchmarks.registration_report.wrong_pair_rates`): a wrong chair accepted below
the right one loses to it, and one that differs from it only where no view looked fits the
evidence as well as the right one (counted apart, ``wrong_unobserved``). Why these rules:
docs/decisions/sensor_benchmark.md.
"""

from __future__ import annotations

from regnf.benchmarks.registration_report import wrong_pair_rates

LEVEL_CHECKS: dict[str, tuple[str, ...]] = {
    "ideal": ("bars",),
    "sensor": ("bars", "discovery"),
    "slam": ("widened",),
    "harsh": (),
}
"""The level-specific checks (see the module); the checks of every level come on top."""

LEVEL_ORDER = tuple(LEVEL_CHECKS)


def _check(name: str, value: str | int, target: str, ok: bool) -> dict:
    return {"check": name, "value": value, "target": target, "pass": bool(ok)}


def summarise(pairs: list[dict], rooms: list[dict], level: str, coverage: str) -> dict:
    """Counts and checks of one level and coverage, from the benchmark's rows.

    Parameters
    ----------
    pairs : list of dict
        Registration rows (:func:`regnf.benchmarks.sensor.register_room`), any levels.
    rooms : list of dict
        Room rows (with ``discovery``: :func:`regnf.benchmarks.discover.score_room`'s row or None).
    level, coverage : str

    Returns
    -------
    dict
        ``level``, ``coverage``, ``pairs``, ``accepted``, ``within_bars``, ``within_widened_bars``
        (both among the accepted), ``accepted_outside_widened_bars``, ``wrong_pairs``,
        ``wrong_accepted`` (every accepted wrong pair), ``wrong_objects_accepted`` (the
        module's rule), ``wrong_unobserved``, ``discovery`` (summed over the rooms, or None),
        ``checks`` (name, value, target, pass) and ``verdict`` (``pass`` when every check
        passes).
    """
    mine = [r for r in pairs if r["level"] == level and r["coverage"] == coverage]
    right = [r for r in mine if not r["wrong_pair"]]
    wrong = [r for r in mine if r["wrong_pair"]]
    n = len(right)
    accepted = sum(bool(r["accepted"]) for r in right)
    in_bars = sum(bool(r["accepted"] and r["within_bars"]) for r in right)
    in_widened = sum(bool(r["accepted"] and r["within_widened_bars"]) for r in right)
    outside = sum(bool(r["accepted"] and not r["within_widened_bars"]) for r in right)
    wrong_objects = unobserved = 0
    for rate in wrong_pair_rates(right + wrong) if wrong else []:
        within_ranked = rate["within_rejected_or_lower"] + rate["within_unidentified_unobserved"]
        wrong_objects += rate["cross_accepted"] + rate["within_pairs"] - within_ranked
        unobserved += rate["within_unidentified_unobserved"]
    found = [r["discovery"] for r in rooms
             if r["level"] == level and r["coverage"] == coverage and r.get("discovery") is not None]
    discovery = None
    if found:
        discovery = {k: sum(d[k] for d in found)
                     for k in ("true_instances", "found", "identified", "within_bars", "false_instances")}
    wanted = LEVEL_CHECKS.get(level, ())
    checks = []
    if "bars" in wanted:
        checks.append(_check("accepted and within the bars", f"{in_bars}/{n}", f"{n}/{n}", in_bars == n))
    if "widened" in wanted:
        checks.append(_check("accepted and within the widened bars", f"{in_widened}/{n}", f"{n}/{n}",
                             in_widened == n))
    checks.append(_check("accepted outside the widened bars", outside, "0", outside == 0))
    if wrong:
        checks.append(_check("wrong objects accepted", wrong_objects, "0", wrong_objects == 0))
    if "discovery" in wanted and discovery is not None:
        total, good = discovery["true_instances"], discovery["within_bars"]
        checks.append(_check("discovery: identified within the bars", f"{good}/{total}",
                             f">= {max(total - 1, 0)}/{total}", good >= total - 1))
        checks.append(_check("discovery: false instances", discovery["false_instances"], "0",
                             discovery["false_instances"] == 0))
    return {"level": level, "coverage": coverage, "pairs": n, "accepted": accepted, "within_bars": in_bars,
            "within_widened_bars": in_widened, "accepted_outside_widened_bars": outside,
            "wrong_pairs": len(wrong), "wrong_accepted": sum(bool(r["accepted"]) for r in wrong),
            "wrong_objects_accepted": wrong_objects if wrong else None, "wrong_unobserved": unobserved,
            "discovery": discovery, "checks": checks,
            "verdict": "pass" if all(c["pass"] for c in checks) else "fail"}


def _num(value: float | None, fmt: str, scale: float = 1.0) -> str:
    return "–" if value is None else format(scale * value, fmt)


def summary_table(summary: list[dict]) -> str:
    """One line per level and coverage: the counts, and each check that failed."""
    out = [("| level | coverage | pairs | accepted | within the bars | within the widened bars | accepted outside "
           "the widened bars | wrong pairs | wrong accepted (wrong objects) | discovery: within the bars / "
           "false | verdict |"), "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summary:
        d = s["discovery"]
        disc = "–" if d is None else f"{d['within_bars']}/{d['true_instances']} / {d['false_instances']}"
        wrong = "–" if not s["wrong_pairs"] else f"{s['wrong_accepted']} ({s['wrong_objects_accepted']})"
        failed = [f"{c['check']} {c['value']} (wanted {c['target']})" for c in s["checks"] if not c["pass"]]
        verdict = "pass" if not failed else "**fail**: " + "; ".join(failed)
        out.append(f"| {s['level']} | {s['coverage']} | {s['pairs']} | {s['accepted']} | {s['within_bars']} | "
                   f"{s['within_widened_bars']} | {s['accepted_outside_widened_bars']} | {s['wrong_pairs']} | "
                   f"{wrong} | {disc} | {verdict} |")
    return "\n".join(out) + "\n"


def room_table(rooms: list[dict]) -> str:
    """One line per room, coverage and level (levels side by side): surface error, discovery, times."""
    out = [("| room | coverage | level | surface mean % | surface p95 % | train s | discovery found / identified "
           "/ within the bars / false | registration s | discovery s | seconds |"),
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rooms, key=lambda r: (r["scene"], r["coverage"], LEVEL_ORDER.index(r["level"]))):
        d = r["discovery"]
        disc = ("–" if d is None else
                f"{d['found']} / {d['identified']} / {d['within_bars']} / {d['false_instances']} of {d['true_instances']}")
        out.append(f"| {r['scene']} | {r['coverage']} | {r['level']} | {100 * r['surface_error_mean_rel']:.3f} | "
                   f"{100 * r['surface_error_p95_rel']:.2f} | {r['train_seconds']:.0f} | {disc} | "
                   f"{r['registration_seconds']:.0f} | {_num(r['discovery_seconds'], '.0f')} | {r['seconds']:.0f} |")
    return "\n".join(out) + "\n"


def pair_table(pairs: list[dict]) -> str:
    """One line per true-box pair, coverage and level (each pair's levels side by side)."""
    out = [("| room | object | coverage | level | cameras | camera Δpos (cm) | camera Δrot (°) | ΔR geo sym (rad) "
           "| Δt (% diag) | Δs (%) | widened bars ΔR / Δt % | conf | accepted | within bars | within widened | s |"),
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    right = [r for r in pairs if not r["wrong_pair"]]
    for r in sorted(right, key=lambda r: (r["scene"], r["object"], r["coverage"], LEVEL_ORDER.index(r["level"]))):
        bars = r["bars_widened"]
        out.append(f"| {r['scene']} | {r['object']} | {r['coverage']} | {r['level']} | {r['cameras']} | "
                   f"{_num(r['camera_position_cm'], '.2f')} | {_num(r['camera_rotation_deg'], '.3f')} | "
                   f"{r['rot_geodesic_sym_rad']:.4f} | {100 * r['trans_rel_diag_sym']:.2f} | "
                   f"{100 * r['scale_rel']:.2f} | {bars['rot_geodesic_sym_rad']:.4f} / "
                   f"{100 * bars['trans_rel_diag_sym']:.2f} | {r['confidence']:.2f} | "
                   f"{'yes' if r['accepted'] else 'no'} | {'yes' if r['within_bars'] else 'no'} | "
                   f"{'yes' if r['within_widened_bars'] else 'no'} | {r['seconds']:.1f} |")
    return "\n".join(out) + "\n"


def wrong_accepts(pairs: list[dict]) -> str:
    """The accepted wrong pairs, one line each (empty when there is none)."""
    lines = [f"- {r['level']}, {r['coverage']} coverage, {r['scene']}: `{r['object']}` in `{r['box_object']}`'s "
             f"box accepted at {r['confidence']:.3f} (difference observed "
             f"{_num(r['difference_observed'], '.2f')})" for r in pairs if r["wrong_pair"] and r["accepted"]]
    return "\n".join(lines) + ("\n" if lines else "")


def markdown_tables(result: dict) -> str:
    """The summary with its verdicts, the rooms, the pairs and the accepted wrong pairs."""
    text = (f"### Verdicts\n\n{summary_table(result['summary'])}\n"
            f"### Rooms\n\n{room_table(result['rooms'])}\n"
            f"### True-box pairs (mesh library)\n\n{pair_table(result['pairs'])}\n")
    wrong = wrong_accepts(result["pairs"])
    if wrong:
        text += f"### Accepted wrong pairs\n\n{wrong}"
    return text
