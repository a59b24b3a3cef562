"""Tables and pictures of the registration benchmark."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError
from regnf.registration.metrics import BARS, within_bars
from regnf.registration.observed_difference import UNOBSERVED
from regnf.registration.result import RegistrationResult

SCENE_RGB = (40, 110, 220)
LIBRARY_RGB = (240, 140, 30)


def _panel(scene_pts: np.ndarray, lib_pts: np.ndarray, axes: tuple[int, int], size: int,
           lo: np.ndarray, span: float) -> Image.Image:
    img = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for pts, rgb in ((lib_pts, LIBRARY_RGB), (scene_pts, SCENE_RGB)):
        uv = (pts[:, axes] - lo[list(axes)]) / span * (size - 8) + 4
        uv[:, 1] = size - uv[:, 1]
        draw.point([tuple(p) for p in uv.tolist()], fill=rgb)
    return img


def before_after_png(result: RegistrationResult, path: Path, size: int = 220) -> None:
    """Scene samples mapped into the library frame (blue) over the library samples (orange):
    front (x-z) and top (x-y) views, before registration (centroids and RMS radii matched, no
    rotation: the raw problem) and after it. Every second scene sample is drawn, so that the
    library shows through where the two agree."""
    if result.samples is None:
        raise RegnfError("the result holds no samples")
    scene, lib = result.samples
    scene = scene[::2]
    c_s, c_l = scene.mean(axis=0), lib.mean(axis=0)
    r_s = np.sqrt(((scene - c_s) ** 2).sum(axis=1).mean())
    r_l = np.sqrt(((lib - c_l) ** 2).sum(axis=1).mean())
    before = (scene - c_s) * (r_l / r_s) + c_l
    after = result.transform.apply(scene)
    allp = np.concatenate([lib, before, after])
    lo = np.percentile(allp, 1, axis=0)
    span = float((np.percentile(allp, 99, axis=0) - lo).max()) or 1.0
    panels = [_panel(s, lib, ax, size, lo, span) for s in (before, after) for ax in ((0, 2), (0, 1))]
    sheet = Image.new("RGB", (size * 4, size), (255, 255, 255))
    for i, p in enumerate(panels):
        sheet.paste(p, (i * size, 0))
    draw = ImageDraw.Draw(sheet)
    for i, text in enumerate(("before: front", "before: top", "after: front", "after: top")):
        draw.text((i * size + 4, 2), text, fill=(0, 0, 0))
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")


def is_reference(row: dict) -> bool:
    """A row of Table I's setting: full coverage, RGB-D library, the box's own object."""
    return (row.get("coverage", "full") == "full" and row.get("library_source", "rgbd") == "rgbd"
            and not row.get("wrong_pair", False))


def table_one(rows: list[dict], paper: dict) -> str:
    """Table I: per pair and method, the symmetric geodesic rotation, translation and scale errors."""
    rows = [r for r in rows if is_reference(r)]
    header = ("| scene | object | method | ΔR geo sym (rad) | Δt (% diag) | Δs (%) | ADD sym (% diag) | "
              "paper ΔR / Δt / Δs | s | conf |")
    out = [header, "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["views"] != "multi":
            continue
        p = paper.get((r["scene"], r["object"])) if r["method"] == "regnf-single" else None
        ptxt = f"{p[1]} / {p[0]} / {p[2]}" if p else ""
        out.append(
            f"| {r['scene']} | {r['object']} | {r['method']} | {r['rot_geodesic_sym_rad']:.4f} | "
            f"{100 * r['trans_rel_diag_sym']:.2f} | {100 * r['scale_rel']:.2f} | {100 * r['add_rel_sym']:.2f} | "
            f"{ptxt} | {r['seconds']:.1f} | {r['confidence']:.2f} |"
        )
    return "\n".join(out) + "\n"


def table_two(rows: list[dict]) -> str:
    """Table II: single uninformative view against multi-view sampling (default method)."""
    rows = [r for r in rows if is_reference(r)]
    multi = {r["object"]: r for r in rows if r["views"] == "multi" and r["method"] == "regnf"}
    out = ["| object | views | ΔR geo sym (rad) | Δt (% diag) | Δs (%) |", "|---|---|---|---|---|"]
    for r in rows:
        if r["views"] != "single":
            continue
        for tag, row in (("single", r), ("multi", multi.get(r["object"]))):
            if row is None:
                continue
            out.append(f"| {r['object']} | {tag} | {row['rot_geodesic_sym_rad']:.4f} | "
                       f"{100 * row['trans_rel_diag_sym']:.2f} | {100 * row['scale_rel']:.2f} |")
    return "\n".join(out) + "\n"


def medians(rows: list[dict]) -> str:
    """Median of each error per method over the Table I pairs."""
    rows = [r for r in rows if is_reference(r)]
    methods = sorted({r["method"] for r in rows if r["views"] == "multi"})
    out = ["| method | median ΔR geo sym (rad) | median Δt (% diag) | median Δs (%) | median s |",
           "|---|---|---|---|---|"]
    for m in methods:
        rs = [r for r in rows if r["method"] == m and r["views"] == "multi"]
        med = {k: float(np.median([r[k] for r in rs]))
               for k in ("rot_geodesic_sym_rad", "trans_rel_diag_sym", "scale_rel", "seconds")}
        out.append(f"| {m} | {med['rot_geodesic_sym_rad']:.4f} | {100 * med['trans_rel_diag_sym']:.2f} | "
                   f"{100 * med['scale_rel']:.2f} | {med['seconds']:.1f} |")
    return "\n".join(out) + "\n"


def _right_rows(rows: list[dict]) -> list[dict]:
    """``regnf`` multi-view rows of the box's own object (no scale sweep), every setting."""
    return [r for r in rows if r["method"] == "regnf" and r["views"] == "multi" and not r.get("wrong_pair")]


def coverage_table(rows: list[dict]) -> str:
    """Per coverage and library source: the 11 pairs accepted, within the bars, median errors, times."""
    out = [("| coverage | library | pairs | accepted | within bars | accepted and within | median ΔR (rad) | "
            "median Δt (% diag) | median Δs (%) | median s | worst s |"), "|---|---|---|---|---|---|---|---|---|---|---|"]
    right = _right_rows(rows)
    for cov, src in sorted({(r.get("coverage", "full"), r.get("library_source", "rgbd")) for r in right}):
        rs = [r for r in right if (r.get("coverage", "full"), r.get("library_source", "rgbd")) == (cov, src)]
        med = {k: float(np.median([r[k] for r in rs])) for k in (*BARS, "seconds")}
        ok = sum(r["accepted"] and within_bars(r) for r in rs)
        out.append(f"| {cov} | {src} | {len(rs)} | {sum(r['accepted'] for r in rs)} | "
                   f"{sum(within_bars(r) for r in rs)} | {ok} | {med['rot_geodesic_sym_rad']:.4f} | "
                   f"{100 * med['trans_rel_diag_sym']:.2f} | {100 * med['scale_rel']:.2f} | "
                   f"{med['seconds']:.1f} | {max(r['seconds'] for r in rs):.1f} |")
    return "\n".join(out) + "\n"


def pair_table(rows: list[dict], coverage: str, source: str) -> str:
    """The 11 pairs of one setting: errors, confidence, accepted."""
    out = ["| scene | object | ΔR geo sym (rad) | Δt (% diag) | Δs (%) | conf | accepted | within bars | s |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in _right_rows(rows):
        if (r.get("coverage", "full"), r.get("library_source", "rgbd")) != (coverage, source):
            continue
        out.append(f"| {r['scene']} | {r['object']} | {r['rot_geodesic_sym_rad']:.4f} | "
                   f"{100 * r['trans_rel_diag_sym']:.2f} | {100 * r['scale_rel']:.2f} | {r['confidence']:.2f} | "
                   f"{'yes' if r['accepted'] else 'no'} | {'yes' if within_bars(r) else 'no'} | {r['seconds']:.1f} |")
    return "\n".join(out) + "\n"


def wrong_pair_rates(rows: list[dict]) -> list[dict]:
    """Per coverage and library source: cross-class false accepts, and within-class ranking.

    A within-class wrong pair (a chair in another chair's box) counts as identified when it
    is rejected or scores a lower confidence than the box's own chair in the same setting;
    ``within_unidentified_unobserved`` counts the others whose difference from the right chair
    the scene never observed (``difference_observed`` below
    :data:`regnf.registration.observed_difference.UNOBSERVED`): no observed evidence ranks those.
    """
    right = {(r["scene"], r["object"], r.get("coverage", "full"), r.get("library_source", "rgbd")): r
             for r in _right_rows(rows)}
    wrong = [r for r in rows if r.get("wrong_pair")]
    out = []
    for cov, src in sorted({(r["coverage"], r["library_source"]) for r in wrong}):
        rs = [r for r in wrong if (r["coverage"], r["library_source"]) == (cov, src)]
        cross = [r for r in rs if _label(r["object"]) != _label(r["box_object"])]
        within = [r for r in rs if r not in cross]
        lower = [r for r in within
                 if not r["accepted"] or r["confidence"] < right[(r["scene"], r["box_object"], cov, src)]["confidence"]]
        unidentified = [r for r in within if r not in lower]
        unobserved = [r for r in unidentified
                      if r.get("difference_observed") is not None and r["difference_observed"] < UNOBSERVED]
        out.append({"coverage": cov, "library_source": src, "cross_pairs": len(cross),
                    "cross_accepted": sum(r["accepted"] for r in cross), "within_pairs": len(within),
                    "within_accepted": sum(r["accepted"] for r in within),
                    "within_rejected_or_lower": len(lower),
                    "within_unidentified_unobserved": len(unobserved),
                    "within_unidentified": [f"{r['scene']}: {r['object']} in {r['box_object']}'s box "
                                            f"({r['confidence']:.4f} vs "
                                            f"{right[(r['scene'], r['box_object'], cov, src)]['confidence']:.4f}; "
                                            f"difference observed {r.get('difference_observed', float('nan')):.2f})"
                                            for r in unidentified]})
    return out


def _label(name: str) -> str:
    from regnf.synthetic.library import make_library_object

    return make_library_object(name).label


def wrong_pair_table(rows: list[dict]) -> str:
    """Markdown of :func:`wrong_pair_rates`."""
    out = [("| coverage | library | cross-class pairs | false accepts | false-accept rate | chair-in-chair pairs | "
            "accepted | rejected or below the right chair | rate | not ranked, difference unobserved |"),
           "|---|---|---|---|---|---|---|---|---|---|"]
    rates = wrong_pair_rates(rows)
    for w in rates:
        out.append(f"| {w['coverage']} | {w['library_source']} | {w['cross_pairs']} | {w['cross_accepted']} | "
                   f"{w['cross_accepted'] / max(1, w['cross_pairs']):.0%} | {w['within_pairs']} | "
                   f"{w['within_accepted']} | {w['within_rejected_or_lower']} | "
                   f"{w['within_rejected_or_lower'] / max(1, w['within_pairs']):.0%} | "
                   f"{w['within_unidentified_unobserved']} |")
    missed = [f"- {w['coverage']} coverage, {w['library_source']} library: {m}"
              for w in rates for m in w["within_unidentified"]]
    if missed:
        out += ["", "Chairs not ranked below the right chair (confidence of the wrong vs the right chair):", *missed]
    return "\n".join(out) + "\n"
