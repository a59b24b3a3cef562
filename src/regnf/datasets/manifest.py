"""The manifest of a generated data set: one JSON row per variant, checked before it is trusted.

``manifest.jsonl`` holds one line per variant, sorted by seed once a run has ended. A row
records what the variant is (seed, status, the library object each instance shows, the
files and their SHA-256) and ends with ``row_sha256``, the digest of everything else in it.
It carries no timing and no absolute path, so two runs of the same settings (on a laptop or
on a cluster) write equal manifests.

On a rerun, a row counts as done only if it parses, its own digest matches, it was made with
the same settings (``config_key``), and for a finished variant every file it lists is on
disk with the listed digest. Anything else (a truncated line, an edited row, a missing or
changed file) is reported and the variant made again.

A run rewrites the manifest whole and atomically when it starts (dropping the rows it will
make again) and when it ends (sorted by seed); in between, each finished variant's row is
appended (:func:`append_row`), so the cost per variant does not grow with the data set. A
run killed in between leaves the rows of its finished variants, in the order they
finished, and at most one torn last line, which the next run reports and makes again.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from regnf.core.atomic_io import write_text

MANIFEST_NAME = "manifest.jsonl"
"""The manifest's file name in the output folder."""
STATUSES = ("ok", "failed")
"""A row's ``status``: the variant's files were written, or its task raised (``error``)."""
REQUIRED = {"seed": int, "status": str, "config_key": str, "row_sha256": str}
"""Keys every row has, with their types."""
REQUIRED_OK = {"variant": str, "layer": str, "selections": dict, "instance_ids": dict, "boxes": dict, "views": int,
               "files": dict}
"""Further keys of a finished variant."""


def sha256_file(path: str | os.PathLike) -> str:
    """SHA-256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def row_digest(row: Mapping[str, Any]) -> str:
    """SHA-256 of a row without its ``row_sha256`` (keys sorted, compact JSON)."""
    body = {k: v for k, v in row.items() if k != "row_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def sealed(row: Mapping[str, Any]) -> dict[str, Any]:
    """``row`` with its ``row_sha256`` set."""
    out = {k: v for k, v in row.items() if k != "row_sha256"}
    out["row_sha256"] = row_digest(out)
    return out


class ManifestState(NamedTuple):
    """A manifest as read back."""

    rows: dict[int, dict[str, Any]]
    """Seed -> a row that passed every check."""
    problems: list[str]
    """One line per rejected row (line number, seed if known, why)."""


def check_row(row: Any, root: Path, config_key: str) -> str | None:
    """Why ``row`` cannot be trusted, or None if it can (see the module)."""
    if not isinstance(row, dict):
        return "not a JSON object"
    for key, kind in REQUIRED.items():
        if not isinstance(row.get(key), kind) or isinstance(row.get(key), bool):
            return f"{key!r} missing or not {kind.__name__}"
    if row["row_sha256"] != row_digest(row):
        return "its row_sha256 does not match its content (the row was changed or damaged)"
    if row["status"] not in STATUSES:
        return f"unknown status {row['status']!r}"
    if row["config_key"] != config_key:
        return f"made with other settings (config_key {row['config_key']}, now {config_key})"
    if row["status"] == "failed":
        return None
    for key, kind in REQUIRED_OK.items():
        if not isinstance(row.get(key), kind):
            return f"{key!r} missing or not {kind.__name__}"
    files = {row["layer"]: row.get("layer_sha256")}
    files.update({f"{row['variant']}/{name}": digest for name, digest in row["files"].items()})
    for rel, digest in files.items():
        path = root / rel
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            return f"file {rel!r} is not inside the output folder"
        if not path.is_file():
            return f"{rel} is missing"
        if sha256_file(path) != digest:
            return f"{rel} differs from the digest the row records"
    return None


def read_manifest(root: str | os.PathLike, config_key: str) -> ManifestState:
    """Read ``root/manifest.jsonl`` and check every row (a missing manifest has no rows).

    A later valid row for a seed replaces an earlier one.
    """
    root = Path(root)
    path = root / MANIFEST_NAME
    rows: dict[int, dict[str, Any]] = {}
    problems: list[str] = []
    if not path.exists():
        return ManifestState(rows, problems)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        return ManifestState(rows, [f"{path}: unreadable ({exc}); every variant is made again"])
    for n, line in enumerate(lines, start=1):  # one line per variant
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            problems.append(f"{path}:{n}: not JSON ({exc.msg})")
            continue
        why = check_row(row, root, config_key)
        seed = row.get("seed") if isinstance(row, dict) else None
        if why is not None:
            problems.append(f"{path}:{n} (seed {seed}): {why}")
            continue
        rows[int(seed)] = row
    return ManifestState(rows, problems)


def write_manifest(root: str | os.PathLike, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write the rows, sorted by seed, as ``root/manifest.jsonl`` (atomically)."""
    path = Path(root) / MANIFEST_NAME
    ordered = sorted(rows, key=lambda r: r["seed"])
    write_text(path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in ordered))
    return path


def append_row(root: str | os.PathLike, row: Mapping[str, Any]) -> Path:
    """Append one row to ``root/manifest.jsonl`` and flush it to disk (see the module).

    One ``write`` of a whole line to a file opened for appending: a kill leaves the line
    whole or torn, never the lines before it changed. The writer must hold the output
    folder's lock, as :func:`regnf.datasets.generation.generate` does.
    """
    path = Path(root) / MANIFEST_NAME
    line = (json.dumps(row, sort_keys=True) + "\n").encode("utf-8")
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        view = memoryview(line)
        while view:  # os.write may write less than asked (a signal, a full pipe)
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)
    return path


def load_rows(out: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of ``out/manifest.jsonl`` as written (unchecked), in seed order.

    During a run (or after a killed one) the file holds rows in the order variants finished;
    they are sorted here.
    """
    path = Path(out) / MANIFEST_NAME
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return sorted(rows, key=lambda r: r["seed"])
