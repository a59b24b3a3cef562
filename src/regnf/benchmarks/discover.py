"""``regnf bench discover``: discovery on the three rooms against their true instances.

Per room and coverage, :func:`~regnf.registration.discovery.discover` runs on the room's
scene field with the whole 8-object library, no boxes given. Each true instance is matched
to the candidate whose box overlaps its true box most (IoU, :func:`box_iou`); it is ``found``
when that IoU is at least :data:`FOUND_IOU` (each candidate matches one instance at most,
greedily by IoU), ``identified`` when that candidate's chosen library object is the
instance's, and ``within_bars`` when the registration's errors against the true pose are
within :data:`regnf.registration.metrics.BARS`. An instance written that matches no true
instance, or another object than its match, is a ``false_instance``.
"""

from __future__ import annotations

import time
from pathlib import Path

from tqdm import tqdm

from regnf.fields.oriented_box import OrientedBox
from regnf.io.checkpoint import load_field
from regnf.registration.discovery import DiscoveryResult, FieldFiles, discover
from regnf.registration.discovery_view import draw_top_view
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.ground_truth import match_boxes, score_discovery

ROOMS = ("ac-room", "atbl-room", "mix-room")
LIBRARY = ("c", "dc", "fc", "fc-nop", "mc", "et", "t", "wt")
"""The whole library: every object of the data set."""
LEAVE_OUT = (("ac-room", "mc"),)
"""(room, object) runs with one object missing from the library: its candidate must stay unmatched."""
FOUND_IOU = 0.5
"""A true instance is found when a candidate's box has at least this IoU with its true box."""


def score_room(scene_name: str, coverage: str, library_source: str, result: DiscoveryResult, scene, library,
               all_instances) -> dict:
    """The benchmark row of one discovery (see the module).

    Instances of objects the library lacks (a leave-one-out run) are not counted as true
    instances: ``left_out`` says what their candidates became (right: ``unmatched``), and an
    instance written there is a false instance.
    """
    instances = [inst for inst in all_instances if inst.library in library]
    left_out = [inst for inst in all_instances if inst.library not in library]
    per_instance, false, matched = score_discovery(result, instances, scene, library, FOUND_IOU)
    boxes = [d.candidate.box for d in result.discoveries]
    gone, _ = match_boxes([OrientedBox.from_corners(inst.box_corners) for inst in left_out],
                          [b for j, b in enumerate(boxes) if j not in matched.values()], FOUND_IOU)
    free = [j for j in range(len(boxes)) if j not in matched.values()]
    left = {}
    for k, inst in enumerate(left_out):
        d = result.discoveries[free[gone[k]]] if k in gone else None
        left[inst.library] = "not found" if d is None else ("unmatched" if d.chosen is None else d.chosen.library_name)
    return {
        "scene": scene_name,
        "coverage": coverage,
        "library_source": library_source,
        "true_instances": len(instances),
        "candidates": len(result.discoveries),
        "found": len(matched),
        "identified": sum(r["identified"] for r in per_instance),
        "within_bars": sum(r["within_bars"] for r in per_instance),
        "false_instances": len(false),
        "unmatched_candidates": len(result.unmatched),
        "skipped_candidates": [d.skipped for d in result.skipped],
        "left_out": left,
        "seconds": float(result.seconds["total"]),
        "seconds_candidates": float(result.seconds["candidates"]),
        "instances": per_instance,
        "false": false,
        "candidate_boxes": [{"size": (2 * d.candidate.box.half_extents).tolist(),
                             "chosen": None if d.chosen is None else d.chosen.library_name,
                             "ambiguous": list(d.ambiguous),
                             "skipped": d.skipped,
                             "tried": [[t.library_name, round(t.screened, 4),
                                        None if t.result is None else round(t.result.confidence, 4)]
                                       for t in d.tried]}
                            for d in result.discoveries],
    }


def run_discover_benchmark(cache: Cache, coverages: tuple[str, ...] = ("full", "low"),
                           library_source: str = "mesh", rooms: tuple[str, ...] = ROOMS,
                           images: Path | None = None, device: str = "cpu",
                           leave_out: tuple[tuple[str, str], ...] = LEAVE_OUT) -> list[dict]:
    """One row per room and coverage (fields are trained into ``cache`` first if missing), and
    one per ``leave_out`` entry (room, object) and coverage: the room with that object missing
    from the library.

    ``images``: a folder for one top view per room and coverage (true boxes dotted).
    """
    paths = {name: cache.object_field(name, library_source, device) for name in LIBRARY}
    for scene_name in rooms:
        for coverage in coverages:
            cache.scene_field(scene_name, coverage, device)
    library = {name: load_field(p, device=device) for name, p in paths.items()}
    rows = []
    jobs = [(s, c, None) for s in rooms for c in coverages]
    jobs += [(s, c, obj) for s, obj in leave_out if s in rooms for c in coverages]
    for scene_name, coverage, lacking in tqdm(jobs, desc="bench discover", disable=not cache.progress):
        capture = cache.room_capture(scene_name, RoomCaptureConfig(coverage=coverage))
        scene_path = cache.scene_field(scene_name, coverage, device)
        scene = load_field(scene_path, device=device)
        t0 = time.perf_counter()
        used = {name: f for name, f in library.items() if name != lacking}
        result = discover(scene, used, files=FieldFiles(scene_path, {n: paths[n] for n in used}))
        row = score_room(scene_name, coverage, library_source, result, scene, used, capture.instances)
        row["wall_seconds"] = time.perf_counter() - t0
        rows.append(row)
        if images is not None and lacking is None:
            truth = [(inst.library, OrientedBox.from_corners(inst.box_corners)) for inst in capture.instances]
            draw_top_view(result, images / f"{scene_name}_{coverage}.png", truth,
                          title=f"{scene_name}, {coverage} coverage, {library_source} library")
    return rows


def markdown_table(rows: list[dict]) -> str:
    """One line per room and coverage, and the misses spelled out."""
    head = ("| scene | library | coverage | true instances | candidates | found | identified | within the bars "
            "| false instances | unmatched candidates | seconds |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = [f"| {r['scene']} | {'all 8' if not r['left_out'] else 'without ' + ', '.join(r['left_out'])} "
             f"| {r['coverage']} | {r['true_instances']} | {r['candidates']} | {r['found']} "
             f"| {r['identified']} | {r['within_bars']} | {r['false_instances']} | {r['unmatched_candidates']} "
             f"| {r['seconds']:.0f} |" for r in rows]
    notes = []
    for r in rows:
        for inst in r["instances"]:
            if inst["within_bars"]:
                continue
            where = f"{r['scene']} ({r['coverage']}) `{inst['object']}`"
            if inst["candidate"] is None:
                notes.append(f"- {where}: not found (best box IoU {inst['iou']:.2f})")
            elif inst.get("ambiguous"):
                a, b = inst["ambiguous"]
                notes.append(f"- {where}: box IoU {inst['iou']:.2f}, left unmatched: `{a}` and `{b}` both fit, and "
                             "they differ only where no view of the scene looked")
            elif not inst["identified"]:
                got = inst["chosen"] or "unmatched"
                notes.append(f"- {where}: box IoU {inst['iou']:.2f}, chosen {got}"
                             + ("" if inst["confidence"] is None else f" ({inst['confidence']:.3f})")
                             + f"; the right object ranked {inst['right_object_screened_rank'] + 1} by the short "
                             "registration" + ("" if inst.get("right_object_confidence") is None
                                               else f", confidence {inst['right_object_confidence']:.3f}"))
            else:
                notes.append(f"- {where}: identified, outside the bars (ΔR {inst['rot_geodesic_rad']:.4f} rad, "
                             f"Δt {100 * inst['trans_rel_diag']:.2f} %, Δs {100 * inst['scale_rel']:.2f} %)")
        for name, became in r["left_out"].items():
            notes.append(f"- {r['scene']} ({r['coverage']}), `{name}` left out of the library: its candidate "
                         f"became {became}")
        for f in r["false"]:
            notes.append(f"- {r['scene']} ({r['coverage']}): false instance `{f['chosen']}` in candidate "
                         f"{f['candidate']}" + ("" if f["matches"] is None else f" (holds `{f['matches']}`)"))
    return head + "\n".join(lines) + "\n" + ("\n" + "\n".join(notes) + "\n" if notes else "")
