"""What discovery writes: each instance's registration with how it was found, and ``discovery.json``.

``regnf discover`` writes ``discovery.json`` (every candidate and what became of it, the
skipped ones with their reasons, the warnings) and one ``registration/candidate_<k>.json``
per identified candidate. ``discovery.json`` lists those files (``files``): a rerun into the
same folder removes the files its previous run listed and that it does not make again
(:func:`recorded_files`), and nothing else there.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from regnf.fields.field import Field
from regnf.fields.oriented_box import OrientedBox
from regnf.registration.discovery import Discovery, DiscoveryResult
from regnf.registration.result import registration_payload

REGISTRATION_FILE = re.compile(r"^registration/candidate_[0-9]+\.json$")
"""The files discovery writes beside ``discovery.json`` (relative paths): only such a file
listed in a previous run's record is ever removed."""


def registration_file(index: int) -> str:
    """The relative path of candidate ``index``'s registration in the output folder."""
    return f"registration/candidate_{int(index)}.json"


def box_json(box: OrientedBox) -> dict:
    """An oriented box as JSON data (``center``, ``half_extents``, ``rotation`` as lists)."""
    return {k: np.asarray(v, dtype=np.float64).tolist() for k, v in box._asdict().items()}


def discovery_record(discovery: Discovery, index: int) -> dict:
    """What an instance's provenance keeps of how it was found (JSON data).

    ``candidate`` is the candidate's index in the result (largest box first),
    ``candidate_box_metres`` its box in scene metres, ``tried`` every library object in the
    short registration's order with its ``screened`` score and, for those refined, the full
    registration's ``confidence`` and ``accepted`` (and its ``error`` when it failed);
    ``chosen`` and ``chosen_confidence`` what became of it (after the refit), ``ambiguous`` the
    two objects it could not tell apart; ``skipped``, only when it could not be examined, why.
    """
    return {
        "found_by": "discovery",
        "candidate": int(index),
        "candidate_box_metres": box_json(discovery.candidate.box),
        "candidate_points": len(discovery.candidate.points),
        "chosen": None if discovery.chosen is None else discovery.chosen.library_name,
        "ambiguous": list(discovery.ambiguous),
        "chosen_confidence": None if discovery.chosen is None else round(float(discovery.chosen.result.confidence), 6),
        **({} if discovery.skipped is None else {"skipped": discovery.skipped}),
        "tried": [{
            "library": t.library_name,
            "screened": round(float(t.screened), 6),
            "confidence": None if t.result is None else round(float(t.result.confidence), 6),
            "accepted": None if t.result is None else bool(t.result.accepted),
            **({} if t.error is None else {"error": t.error}),
        } for t in discovery.tried],
    }


def instance_payloads(result: DiscoveryResult, scene_field: Field, library: Mapping[str, Field],
                      scene_path: str | os.PathLike, library_paths: Mapping[str, str | os.PathLike]
                      ) -> list[tuple[int, dict]]:
    """(candidate index, registration JSON) of every identified candidate: what ``regnf
    register --out`` writes (its ``warnings`` included), with the ``discovery`` record
    (:func:`discovery_record`) that the stage keeps as the instance's provenance."""
    out = []
    for i, d in enumerate(result.discoveries):
        if d.chosen is None:
            continue
        name = d.chosen.library_name
        payload = registration_payload(d.chosen.result, scene_field, library[name], scene_path, library_paths[name])
        payload["discovery"] = discovery_record(d, i)
        out.append((i, payload))
    return out


def discovery_json(result: DiscoveryResult, payloads: list[tuple[int, dict]], written: Mapping[int, str],
                   files: list[str], header: Mapping[str, object]) -> dict:
    """The content of ``discovery.json``.

    Parameters
    ----------
    result : DiscoveryResult
    payloads : list of (int, dict)
        :func:`instance_payloads` of ``result``.
    written : mapping of int -> str
        Candidate index -> the stage instance it became.
    files : list of str
        The files this run wrote besides ``discovery.json`` (relative paths).
    header : mapping
        What comes first (the fields, the stage).

    Returns
    -------
    dict
        ``header``; ``seconds``; ``support_planes``; ``candidates`` (:func:`discovery_record`
        with ``stage_instance`` and ``warnings``); ``skipped`` (``candidate``, ``box_metres``
        and ``reason`` of each candidate that could not be examined); ``warnings`` (``candidate
        k (object): warning``, every instance's); ``files``.
    """
    warned = {i: payload.get("warnings", []) for i, payload in payloads}
    chosen = {i: payload["library_name"] for i, payload in payloads}
    return {
        **header,
        "seconds": result.seconds,
        "support_planes": len(result.found.supports),
        "candidates": [{**discovery_record(d, i), "stage_instance": written.get(i), "warnings": warned.get(i, [])}
                       for i, d in enumerate(result.discoveries)],
        "skipped": [{"candidate": i, "box_metres": box_json(d.candidate.box), "reason": d.skipped}
                    for i, d in enumerate(result.discoveries) if d.skipped is not None],
        "warnings": [f"candidate {i} ({chosen[i]}): {w}" for i in sorted(warned) for w in warned[i]],
        "files": sorted(files),
    }


def recorded_files(record: Path) -> set[str]:
    """The files a previous run listed in its ``discovery.json`` (``record``), relative paths.

    Only paths of :data:`REGISTRATION_FILE` are taken. A record without ``files`` (written
    before it had them) lists the registrations of its identified candidates; an unreadable or
    missing record lists nothing.
    """
    try:
        data = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return set()
    if not isinstance(data, dict):
        return set()
    files = data.get("files")
    if files is None and isinstance(data.get("candidates"), list):
        files = [registration_file(c["candidate"]) for c in data["candidates"]
                 if isinstance(c, dict) and c.get("chosen") is not None and isinstance(c.get("candidate"), int)]
    if not isinstance(files, list):
        return set()
    return {f for f in files if isinstance(f, str) and REGISTRATION_FILE.match(f)}


def remove_stale(folder: Path, previous: set[str], kept: set[str]) -> list[str]:
    """Remove the files of ``previous`` that are not in ``kept`` from ``folder`` (plain files and
    links only; a folder of that name is the user's); return those removed."""
    removed = []
    for rel in sorted(previous - kept):
        path = folder / rel
        if path.is_symlink() or path.is_file():
            path.unlink()
            removed.append(rel)
    return removed
